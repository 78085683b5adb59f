"""The step a fit keeps (fitting.selection): held-back training frames leave the training set, are scored every
``train.select_every`` steps, and the best-scoring weights are the ones evaluated (``train.keep``)."""

import json
import math

import pytest
import torch

from fitting.checkpoint import load_checkpoint, save_checkpoint
from fitting.config import ConfigError, load_config
from fitting.fitted import load_fitted
from fitting.losses import ray_loss
from fitting.run_folder import prepare_run_dir
from fitting.selection import Selection, kept_weights, paired_error_db
from narf.metrics import psnr
from pipelines.runs.fit import start_run
from pipelines.runs.subject.session import split_holdout


def test_split_holdout_takes_the_middle_of_every_n():
    config = load_config("tiny", ["train.holdout_every=4"])
    assert split_holdout(list(range(10)), config.train) == ([0, 1, 3, 4, 5, 7, 8, 9], [2, 6])
    assert split_holdout(list(range(10)), load_config("tiny").train) == (list(range(10)), [])
    # fewer than 2n frames: none held back, so a short capture loses no frame to the choice of step
    assert split_holdout([5, 6, 7], load_config("tiny", ["train.holdout_every=2"]).train) == ([5, 6, 7], [])
    assert split_holdout(list(range(7)), config.train) == (list(range(7)), [])
    assert split_holdout(list(range(8)), config.train) == ([0, 1, 3, 4, 5, 7], [2, 6])


def test_the_best_score_keeps_its_weights():
    model = torch.nn.Linear(2, 1)
    selection = Selection(views=None, rays=None)
    assert selection.update(10, torch.full((8,), 10 ** (-1.2)), model)  # 12 dB
    kept = {k: v.clone() for k, v in model.state_dict().items()}
    with torch.no_grad():
        model.weight += 1
    assert not selection.update(20, torch.full((8,), 10 ** (-1.1)), model)  # 11 dB, worse: the step-10 weights stay
    assert selection.best_step == 10 and torch.equal(selection.best_model["weight"], kept["weight"])
    assert selection.history == [(10, pytest.approx(12.0)), (20, pytest.approx(11.0))]
    state = {"model": model.state_dict(), "step": 20, "selection": selection.state()}
    assert kept_weights(state, "best")[1] == 10 and kept_weights(state, "last")[1] == 20
    assert kept_weights({"model": {}, "step": 7}, "best")[1] == 7  # no holdout: the last


def test_the_paired_standard_error_by_hand():
    """reference 0.01 on 4 rays, d = (2, 0, 2, 0) x 1e-3: mean(d) = 1e-3, std(d) = 1e-3 sqrt(4 / 3) (Bessel),
    SE = std / 2 = 5.7735e-4, in dB 10 / ln 10 x SE / 0.01 = 0.25074 dB; the scores differ by 10 log10 1.1 =
    0.41393 dB."""
    reference = torch.full((4,), 0.01)
    errors = reference + torch.tensor([2e-3, 0.0, 2e-3, 0.0])
    assert paired_error_db(errors, reference) == pytest.approx(0.25074, rel=1e-4)  # float32 inputs, sums in float64
    assert paired_error_db(errors, None) == 0.0 and paired_error_db(errors, reference[:3]) == 0.0


@pytest.mark.parametrize("margin, kept", [(0.0, 10), (1.0, 10), (2.0, 20)])
def test_a_later_score_within_the_margin_is_kept(margin, kept):
    """The step-20 score lies 0.414 dB below the leader's, 1.65 paired standard errors (the values above): kept
    with a margin of 2, not of 1 or 0. The leader stays step 10 either way, and a step 30 far below it (0 spread,
    1.46 dB below) keeps what was kept."""
    model = torch.nn.Linear(2, 1)
    selection = Selection(views=None, rays=None, margin=margin)
    reference = torch.full((4,), 0.01)
    assert selection.update(10, reference, model)
    assert selection.update(20, reference + torch.tensor([2e-3, 0.0, 2e-3, 0.0]), model) == (kept == 20)
    assert not selection.update(30, reference * 1.4, model)
    assert (selection.best_step, selection.leader_step) == (kept, 10)
    assert selection.best_psnr == pytest.approx(20.0 if kept == 10 else 20 - 10 * math.log10(1.1))
    assert selection.update(40, reference * 0.9, model)  # a new leader is kept at any margin
    assert selection.best_step == selection.leader_step == 40


def test_a_restored_selection_keeps_its_leader():
    model = torch.nn.Linear(2, 1)
    selection = Selection(views=None, rays=None, margin=2.0)
    selection.update(10, torch.full((4,), 0.01), model)
    selection.update(20, torch.full((4,), 0.01) + torch.tensor([2e-3, 0.0, 2e-3, 0.0]), model)
    restored = Selection(views=None, rays=None, margin=2.0)
    restored.restore(selection.state())
    assert (restored.best_step, restored.leader_step) == (20, 10)
    assert torch.equal(restored.leader_errors, selection.leader_errors)
    # a checkpoint from before the margin: its best is the leader, with no errors to pair against
    old = {"best_step": 10, "best_psnr": 20.0, "model": None, "history": [[10, 20.0]]}
    restored.restore(old)
    assert (restored.leader_step, restored.leader_psnr, restored.leader_errors) == (10, 20.0, None)


def test_a_fit_with_held_back_frames_scores_them_and_is_evaluated_at_its_best_step(data_root_64, tmp_path):
    sets = [f"data.data_root={data_root_64}", "data.ratio=1.0", "train.steps=12", "train.holdout_every=4"]
    config = load_config("tiny", [*sets, "train.select_every=4", "train.log_every=100"])
    run = prepare_run_dir(tmp_path / "run", False)
    trainer = start_run(run, torch.device("cpu"), config, progress=False)
    held = {2, 6}  # the "narf" protocol trains on the first 9 of 10 frames; frames 2 and 6 are held back
    # 2 frames x the one training camera (views 0, 6, 12, 18 of 4 cameras)
    assert not held & set(trainer.frames) and len(trainer.fit_data.selection) == 2
    trainer.fit()
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    scored = [(row["step"], row["select_psnr"]) for row in rows if "select_psnr" in row]
    assert [step for step, _ in scored] == [4, 8, 12]  # select_every, and rows between log_every's
    state = load_checkpoint(run)
    best_step, best = max(scored, key=lambda item: item[1])
    assert state["selection"]["best_step"] == best_step and state["selection"]["best_psnr"] == pytest.approx(best)
    fitted = load_fitted(run)
    assert fitted.kept_step == best_step
    for name, value in fitted.field.state_dict().items():
        assert torch.equal(value, state["selection"]["model"][name]), name
    # the score is the field's: rendering the same fixed rays again gives the same PSNR (deterministic samples)
    trainer.field.load_state_dict(state["selection"]["model"])
    score = trainer.selection.score(config, trainer.field, trainer.colour_response)
    assert score == pytest.approx(best, abs=1e-4)  # float32 sums over 4,096 rays
    # the rays' errors average to the training loss's colour MSE over the same rays (fitting.losses.ray_loss)
    trainer.field.eval()
    with torch.no_grad():
        r = config.render
        rays, poses = trainer.selection.rays, trainer.selection.views.poses
        _, colour = ray_loss(config, trainer.field, rays, poses, None, r.eval_coarse, r.eval_fine, randomized=False)
    assert psnr(colour).item() == pytest.approx(score, abs=1e-4)  # the same float32 sums, grouped otherwise
    assert all(row["select_se_db"] >= 0 for row in rows if "select_psnr" in row)
    # render.val_*: the score is the render at the validation's own counts, not the evaluation's
    cheaper = load_config("tiny", [*sets, "render.val_coarse=4", "render.val_fine=2"])
    assert config.render.validation_samples() == (r.eval_coarse, r.eval_fine) == (8, 8)
    assert cheaper.render.validation_samples() == (4, 2)
    with torch.no_grad():
        _, colour = ray_loss(cheaper, trainer.field, rays, poses, None, 4, 2, randomized=False)
    cheap_score = trainer.selection.score(cheaper, trainer.field, trainer.colour_response)
    assert cheap_score == pytest.approx(psnr(colour).item(), abs=1e-4)  # as above
    assert abs(cheap_score - score) > 1e-3  # another estimator of the same field: the counts were used


def test_evaluation_loads_the_kept_weights_not_the_last(tiny_run, tmp_path):
    """A checkpoint whose selection kept other weights (here the last ones plus 1, at step 1): ``keep: best`` loads
    those, at their step's window; ``keep: last`` the last."""
    state = load_checkpoint(tiny_run)
    best = {k: v + 1 if v.is_floating_point() else v for k, v in state["model"].items()}
    state["selection"] = {"best_step": 1, "best_psnr": 20.0, "model": best, "history": [[1, 20.0], [2, 19.0]]}
    for keep, weights, step in (("best", best, 1), ("last", state["model"], 2)):
        state["config"]["train"]["keep"] = keep
        save_checkpoint(tmp_path / keep, state)
        fitted = load_fitted(tmp_path / keep)
        assert fitted.kept_step == step
        for name, value in fitted.field.state_dict().items():
            assert torch.equal(value, weights[name]), (keep, name)


@pytest.mark.parametrize("stop", [6, 7])
def test_a_fit_that_runs_out_of_time_logs_the_score_of_its_last_step(data_root_64, tmp_path, monkeypatch, stop):
    """The time budget ends the fit after ``stop`` steps: its last step is scored, and that score is in the log,
    in the row of that step (step 6 was logged by ``log_every``: the row gains the score; step 7 was not: a row is
    added), each step once."""
    import fitting.trainer

    class Stops(fitting.trainer.Budget):
        ticks = 0

        def tick(self, agree=float):
            Stops.ticks += 1

        @property
        def out_of_time(self):
            return Stops.ticks > stop

    monkeypatch.setattr(fitting.trainer, "Budget", Stops)
    sets = [f"data.data_root={data_root_64}", "data.ratio=1.0", "train.steps=20", "train.holdout_every=4"]
    config = load_config("tiny", [*sets, "train.select_every=4", "train.log_every=3"])
    run = prepare_run_dir(tmp_path / "run", False)
    trainer = start_run(run, torch.device("cpu"), config, progress=False)
    result = trainer.fit(max_minutes=1.0)
    assert result.step == stop and not result.finished
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    steps = [row["step"] for row in rows]
    assert steps == sorted(set(steps)) and steps[-1] == stop  # each step once, in order, the last one last
    assert [row["step"] for row in rows if "select_psnr" in row] == [4, stop]
    assert rows[-1]["select_psnr"] == pytest.approx(trainer.selection.history[-1][1])
    assert rows[-1]["loss"] == pytest.approx(result.loss)


def test_a_negative_margin_is_refused():
    with pytest.raises(ConfigError, match="select_margin"):
        load_config("tiny", ["train.select_margin=-1"])
    assert load_config("cpu").train.select_margin == 2.0 and load_config("tiny").train.select_margin == 0.0


def test_the_validation_previews_render_at_the_validation_counts(monkeypatch, tmp_path):
    """RUN/val/'s previews (fitting.plots.write_validation) are rendered with ``render.val_*``, the evaluation's
    counts when ``val_coarse`` is 0; the config they are given is not changed."""
    import numpy as np

    import fitting.evaluate
    from fitting.plots import write_validation

    seen = []

    def fake_render(field, camera, pose, config, latent=None):
        seen.append((config.render.eval_coarse, config.render.eval_fine))
        return {"rgb": torch.zeros(2, 3, 3), "mask": torch.zeros(2, 3), "depth": torch.zeros(2, 3)}

    monkeypatch.setattr(fitting.evaluate, "render_view", fake_render)
    image = np.zeros((2, 3, 3), np.float32)
    for sets, counts in (([], (8, 8)), (["render.val_coarse=4", "render.val_fine=2"], (4, 2))):
        config = load_config("tiny", sets)
        write_validation(None, config, image, None, None, tmp_path / f"{counts[0]}.png")
        assert seen[-1] == counts and (config.render.eval_coarse, config.render.eval_fine) == (8, 8)
