"""The colour of frames a fit did not train on (docs/model.md §4, *Colour of frames not trained on*), and narf-eval's
other overrides of a run's evaluation (--samples, --frame-step)."""

import dataclasses

import torch

from pipelines.runs.subject.session import load_run, poses_for_frames


def test_novel_frames_take_the_nearest_trained_frames_pose_features_and_trained_frames_keep_theirs(tiny_run):
    loaded = load_run(tiny_run)
    trained = loaded.trained_frames()
    novel = [f for f in range(loaded.capture.n_frames) if f not in trained]
    assert trained and novel  # the tiny capture's narf protocol: frames 0..8 train, 9 is a novel pose
    frames = [trained[0], novel[0], trained[-1]]
    poses, _, _ = poses_for_frames(loaded, loaded.body_model, frames)
    bank, _, _ = poses_for_frames(loaded, loaded.body_model, trained)
    coloured = loaded.colour_poses(poses, frames)
    assert torch.equal(coloured.pose_features[[0, 2]], poses.pose_features[[0, 2]])  # trained: their own, exactly
    here = poses.world_from_part[1, 0, :3, 3].double()
    gaps = [float((bank.world_from_part[k, 0, :3, 3].double() - here).norm()) for k in range(len(trained))]
    nearest = min(range(len(trained)), key=gaps.__getitem__)  # by hand, in float64
    assert torch.equal(coloured.pose_features[1], bank.pose_features[nearest])
    assert not torch.equal(coloured.pose_features[1], poses.pose_features[1])
    assert torch.equal(coloured.world_from_part, poses.world_from_part)  # the geometry's inputs are untouched
    other = loaded.colour_poses(poses)  # no capture frames (another recording, a new motion): every frame borrows
    assert torch.equal(other.pose_features[0], bank.pose_features[0])  # trained[0] stands at itself
    model = dataclasses.replace(loaded.config.model, novel_colour="own")
    loaded.config = dataclasses.replace(loaded.config, model=model)
    assert loaded.colour_poses(poses, frames) is poses  # the paper's: each frame its own


def test_narf_eval_records_the_novel_colour_and_its_flag_overrides_the_run(tiny_run, tmp_path):
    """narf-eval --novel-colour: each split records which colour it was scored with; the training frames' own
    views are the same either way, to the bit (they keep their own pose features)."""
    import json
    import shutil

    from pipelines.cli import eval as cli_eval
    from pipelines.cli.common import run_cli

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    shutil.rmtree(run / "eval", ignore_errors=True)
    argv = ["--run", str(run), "--split", "same_pose_same_view", "--split", "novel_pose", "--limit", "1", "--quiet"]
    reports = []
    for extra in ([], ["--novel-colour", "own"]):
        assert run_cli("narf-eval", cli_eval.main, [*argv, "--grids", "0", *extra]) == 0
        reports.append(json.loads((run / "eval" / "metrics.json").read_text())["splits"])
    assert [r["novel_pose"]["novel_colour"] for r in reports] == ["nearest", "own"]
    assert reports[0]["same_pose_same_view"]["per_view"] == reports[1]["same_pose_same_view"]["per_view"]


def test_narf_eval_samples_override_the_runs_render_counts(tiny_run, tmp_path, capsys):
    """narf-eval --samples COARSE FINE renders with those counts (recorded in metrics.json and named in metrics.md)
    in place of the run's render.eval_*; the checkpoint is not changed, and bad counts are one line, exit 2."""
    import json
    import shutil

    from pipelines.cli import eval as cli_eval
    from pipelines.cli.common import run_cli

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    shutil.rmtree(run / "eval", ignore_errors=True)
    checkpoint = (run / "checkpoint.pt").read_bytes()
    argv = ["--run", str(run), "--split", "novel_pose", "--limit", "1", "--grids", "0", "--quiet"]
    reports = []
    for extra in ([], ["--samples", "4", "2"]):
        assert run_cli("narf-eval", cli_eval.main, [*argv, *extra]) == 0
        reports.append(json.loads((run / "eval" / "metrics.json").read_text()))
    assert [r["samples"] for r in reports] == [[8, 8], [4, 2]]  # the tiny preset's counts, then the flag's
    assert "4 + 2 samples a ray" in (run / "eval" / "metrics.md").read_text()
    psnrs = [r["splits"]["novel_pose"]["full"]["psnr"] for r in reports]
    assert psnrs[0] != psnrs[1]  # another estimator of the same field
    assert (run / "checkpoint.pt").read_bytes() == checkpoint
    capsys.readouterr()
    assert run_cli("narf-eval", cli_eval.main, [*argv, "--samples", "1", "8"]) == 2
    assert "--samples 1 8: COARSE must be >= 2" in capsys.readouterr().err


def test_narf_eval_frame_step_takes_every_nth_frame_of_a_split(tiny_run, tmp_path, capsys):
    """narf-eval --frame-step N scores every Nth frame of the split's frames in place of the protocol's interval (the
    tiny capture's narf protocol: 9 training frames, 1 novel, so every frame by default: docs/formats.md §1.8) and
    records it; with --capture (every frame of another recording) it is one line, exit 2."""
    import json
    import shutil

    from pipelines.cli import eval as cli_eval
    from pipelines.cli.common import run_cli

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    shutil.rmtree(run / "eval", ignore_errors=True)
    argv = ["--run", str(run), "--split", "same_pose_same_view", "--grids", "0", "--quiet"]
    splits = []
    for extra in ([], ["--frame-step", "4"]):
        assert run_cli("narf-eval", cli_eval.main, [*argv, *extra]) == 0
        splits.append(json.loads((run / "eval" / "metrics.json").read_text())["splits"]["same_pose_same_view"])
    assert [s["frame_step"] for s in splits] == [1, 4]
    assert [sorted({v["frame"] for v in s["per_view"]}) for s in splits] == [list(range(9)), [0, 4, 8]]
    assert {v["camera"] for v in splits[1]["per_view"]} == {v["camera"] for v in splits[0]["per_view"]}
    assert "(frame step 4)" in (run / "eval" / "metrics.md").read_text()
    capsys.readouterr()
    argv = ["--run", str(run), "--capture", str(tmp_path), "--frame-step", "2", "--quiet"]
    assert run_cli("narf-eval", cli_eval.main, argv) == 2
    assert "as the split 'capture'" in capsys.readouterr().err


def test_narf_render_video_samples_override_the_runs_render_counts(tiny_run, tmp_path, capsys, monkeypatch):
    """narf-render-video --samples COARSE FINE renders every frame with those counts in place of the run's
    render.eval_* (the tiny preset's 8 + 8 without it), as narf-eval --samples; bad counts are one line, exit 2."""
    import shutil

    import pipelines.runs.subject.video as subject_video
    from pipelines.cli import render_video as cli_video
    from pipelines.cli.common import run_cli

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    counts, render_view = [], subject_video.render_view

    def counted(field, camera, pose, config, *rest, **kwargs):
        counts.append((config.render.eval_coarse, config.render.eval_fine))
        return render_view(field, camera, pose, config, *rest, **kwargs)

    monkeypatch.setattr(subject_video, "render_view", counted)
    argv = ["--run", str(run), "--kind", "orbit", "--frames", "2", "--quiet"]
    assert run_cli("narf-render-video", cli_video.main, argv) == 0
    assert run_cli("narf-render-video", cli_video.main, [*argv, "--samples", "4", "2"]) == 0
    assert counts == [(8, 8)] * 2 + [(4, 2)] * 2
    capsys.readouterr()
    assert run_cli("narf-render-video", cli_video.main, [*argv, "--samples", "8", "-1"]) == 2
    assert "--samples 8 -1: COARSE must be >= 2 and FINE >= 0" in capsys.readouterr().err
