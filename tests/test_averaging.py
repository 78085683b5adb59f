"""The weights' moving average (fitting.averaging, ``train.ema_decay``): the recursion by hand, the weights it hands
to the selection and the evaluation, a resumed fit, and a training run it leaves unchanged."""

import json

import pytest
import torch

from fitting.averaging import WeightAverage, averaged_weights
from fitting.checkpoint import load_checkpoint
from fitting.config import ConfigError, load_config
from fitting.fitted import load_fitted
from fitting.run_folder import prepare_run_dir
from fitting.selection import kept_weights
from pipelines.runs.fit import resume_run, start_run


def test_the_average_follows_the_recursion_by_hand():
    """W̄_0 = W_0, W̄_t = β W̄_{t-1} + (1 - β) W_t: with β = 0.5 and W = 0, then 4, then 8, the average is 0, 2, 5
    (exact in binary floating point); buffers are the module's own."""
    module = torch.nn.BatchNorm1d(1)  # one weight, one bias, running statistics as buffers
    with torch.no_grad():
        module.weight.zero_()
    average = WeightAverage(module, 0.5)
    for value, expected in ((4.0, 2.0), (8.0, 5.0)):
        with torch.no_grad():
            module.weight.fill_(value)
        average.update(module)
        assert average.average["weight"].item() == expected
    with torch.no_grad():
        module.running_mean.fill_(3.0)
    with average.applied(module):
        assert module.weight.item() == 5.0 and module.running_mean.item() == 3.0
    assert module.weight.item() == 8.0  # its own weights back after the block
    assert average.updates == 2


def test_the_average_is_checked_on_the_way_in():
    with pytest.raises(ValueError, match="decay in"):
        WeightAverage(torch.nn.Linear(1, 1), 1.0)
    with pytest.raises(ConfigError, match="train.ema_decay"):
        load_config("tiny", ["train.ema_decay=1.0"])
    other = WeightAverage(torch.nn.Linear(1, 1), 0.9)
    with pytest.raises(ValueError, match="does not fit"):
        other.restore({"updates": 1, "average": {"weight": torch.zeros(1, 1)}})


def test_a_run_is_evaluated_with_its_average():
    """``keep: last`` of a checkpoint with an average gives the average's weights; without one, the last."""
    state = {"model": {"w": torch.zeros(2), "b": torch.ones(1)}, "step": 5}
    assert kept_weights(state, "last")[0] is state["model"]
    state["weight_average"] = {"decay": 0.9, "updates": 5, "average": {"w": torch.full((2,), 0.5)}}
    weights, step = kept_weights(state, "last")
    assert step == 5 and torch.equal(weights["w"], torch.full((2,), 0.5)) and torch.equal(weights["b"], torch.ones(1))
    assert averaged_weights({"model": {}, "step": 1}) is None


def test_a_fit_with_the_average_trains_the_same_weights_and_keeps_the_average(data_root_64, tmp_path):
    """The average changes no training step (the raw weights of both fits agree to the bit), the held-back frames
    score the average (its raw score logged beside), the checkpoint holds it, and the run is evaluated with it."""
    sets = [f"data.data_root={data_root_64}", "data.ratio=1.0", "train.steps=8", "train.holdout_every=4"]
    states = {}
    for decay in (0.0, 0.8):
        config = load_config("tiny", [*sets, "train.select_every=4", "train.log_every=100", f"train.ema_decay={decay}"])
        run = prepare_run_dir(tmp_path / f"run{decay}", False)
        trainer = start_run(run, torch.device("cpu"), config, progress=False)
        trainer.fit()
        states[decay] = (run, load_checkpoint(run), trainer)
    (plain_run, plain, _), (run, state, trainer) = states[0.0], states[0.8]
    for name, value in plain["model"].items():
        assert torch.equal(value, state["model"][name]), name
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    plain_rows = [json.loads(line) for line in (plain_run / "log.jsonl").read_text().splitlines()]
    scored = [row for row in rows if "select_psnr" in row]
    # the raw weights' score is the plain fit's (the same weights, the same rays)
    assert [row["select_psnr_raw"] for row in scored] == [
        row["select_psnr"] for row in plain_rows if "select_psnr" in row
    ]
    average = state["weight_average"]["average"]
    assert state["weight_average"]["updates"] == 8
    assert any(not torch.equal(average[name], state["model"][name]) for name in average)
    best = state["selection"]["model"]
    if state["selection"]["best_step"] == 8:  # the kept weights are the average of their step
        assert all(torch.equal(best[name], average[name]) for name in average)
    with trainer.kept_weights():  # the average scores what the log says
        score = trainer.selection.score(trainer.config, trainer.field, trainer.colour_response)
    assert score == pytest.approx(scored[-1]["select_psnr"], abs=1e-4)  # float32 sums over 4,096 rays
    fitted = load_fitted(run)
    for name, value in fitted.field.state_dict().items():
        assert torch.equal(value, best[name]), name


def test_a_resumed_fit_continues_the_average(data_root_64, tmp_path):
    """A fit stopped after 4 steps and resumed to 8 ends with the average of an uninterrupted 8-step fit (the tiny
    preset's rate does not depend on the budget, so both fits take the same steps)."""
    sets = [f"data.data_root={data_root_64}", "data.ratio=1.0", "train.ema_decay=0.7", "train.log_every=100"]
    whole = prepare_run_dir(tmp_path / "whole", False)
    start_run(whole, torch.device("cpu"), load_config("tiny", [*sets, "train.steps=8"]), progress=False).fit()
    split = prepare_run_dir(tmp_path / "split", False)
    start_run(split, torch.device("cpu"), load_config("tiny", [*sets, "train.steps=4"]), progress=False).fit()
    resume_run(split, torch.device("cpu"), ["train.steps=8"], progress=False).fit()
    expected, got = load_checkpoint(whole)["weight_average"], load_checkpoint(split)["weight_average"]
    assert got["updates"] == expected["updates"] == 8
    for name, value in expected["average"].items():
        assert torch.equal(value, got["average"][name]), name
