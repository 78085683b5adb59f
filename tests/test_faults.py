"""Faults (docs/design.md, "Files"): a command killed at any moment leaves its output absent, as it was, or complete,
and runs again to the end; a full disk ends in one line naming the file, with the last good output intact; one writer
per folder. Kills are SIGKILL of a child process at seeded random moments."""

import errno
import functools
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import spawn
import torch

from fitting.checkpoint import load_checkpoint
from fitting.files import FolderBusy, folder_lock, publish_folder, restore_replaced
from fitting.view_store import ViewStore
from pipelines.cli import fit as cli_fit
from pipelines.cli.common import _message, run_cli

STEPS = 240
#: how long a command may run before the test calls it hung: far above what any of them takes (a guard, not a
#: measurement), so that a loaded 2-core machine passes as an idle one does
HANG = 1200


def _command(module: str, *argv) -> list[str]:
    return [sys.executable, "-c", f"from pipelines.cli.{module} import entrypoint; entrypoint()", *map(str, argv)]


def _fit_command(root: Path, out: Path) -> list[str]:
    sets = ["data.ratio=1.0", f"train.steps={STEPS}", "train.checkpoint_minutes=0", "train.log_every=5"]
    flags = [item for s in sets for item in ("--set", s)]
    return _command("fit", "--config", "tiny", "--data-root", root, "--out", out, "--quiet", *flags)


def _kill_when(argv: list[str], ready, delay: float) -> int | None:
    """Start ``argv`` and SIGKILL it ``delay`` s after ``ready()`` first holds (an event in its output, never a time
    since its start, so a fast or a loaded machine kills it at the same point of its work); its exit code when it
    ended first."""
    process = spawn.popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + HANG
    while process.poll() is None and time.time() < deadline and not ready():
        time.sleep(0.005)
    time.sleep(delay)
    if process.poll() is not None:
        return process.returncode
    os.kill(process.pid, signal.SIGKILL)
    spawn.finish(process, 30, f"{argv[3]} after SIGKILL")
    return None


def _logged_step(out: Path) -> int:
    """The last step in the run's log (0 before the first row)."""
    try:
        lines = (out / "log.jsonl").read_text().splitlines()
        return json.loads(lines[-1])["step"] if lines else 0
    except (FileNotFoundError, json.JSONDecodeError, KeyError):  # a row being written
        return 0


@pytest.mark.slow
def test_a_fit_killed_at_random_moments_resumes_to_the_uninterrupted_result(data_root_64, tmp_path):
    """Six SIGKILLs, the first right after the first checkpoint, the others at seeded steps of the resumed fits
    (tied to its log, so they land at the same points of the work on any machine; checkpoints every step, so many
    land while one is being written), each followed by ``--resume``: the fit ends at its last step with the weights
    of an uninterrupted fit, and its log holds each logged step once, in order."""
    straight, out = tmp_path / "straight", tmp_path / "killed"
    assert spawn.run(_fit_command(data_root_64, straight), HANG).returncode == 0
    first = _kill_when(_fit_command(data_root_64, out), lambda: (out / "checkpoint.pt").exists(), 0.0)
    assert first is None, "the fit ended before its first checkpoint was seen"
    rng, resume = random.Random(0), [*_command("fit", "--out", out, "--resume", "--quiet")]
    kills = [load_checkpoint(out)["step"]]
    # five kills at seeded steps, 40 steps apart, each a few milliseconds after its step's log row: in the step
    # after it or in its checkpoint's write
    for k in range(5):
        step = 20 + 40 * k + rng.randrange(0, 30, 5)
        reached = functools.partial(lambda at: _logged_step(out) >= at, step)
        assert _kill_when(resume, reached, rng.uniform(0.0, 0.02)) is None, step
        kills.append(load_checkpoint(out)["step"])  # the visible checkpoint is always a whole one
    assert spawn.run(resume, HANG).returncode == 0
    assert kills == sorted(set(kills)) and kills[-1] < STEPS, kills  # six kills, each at a later checkpoint
    a, b = load_checkpoint(straight), load_checkpoint(out)
    assert a["step"] == b["step"] == STEPS
    for key, value in a["model"].items():
        # the resumed fit replays the same batches and jitter; only float32 reduction order may differ between
        # processes (thread scheduling): ~eps32 per step on weights ~1, far below 1e-5 over 240 steps
        assert torch.allclose(value, b["model"][key], atol=1e-5), key
    steps = [json.loads(line)["step"] for line in (out / "log.jsonl").read_text().splitlines()]
    assert steps == list(range(5, STEPS + 1, 5)), steps
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # no temporary file left


class _FullDisk:
    """An open file whose writes find the disk full, as ``write(2)`` reports it (no file name)."""

    def __init__(self, handle):
        self.handle = handle

    def write(self, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.handle.close()

    def __getattr__(self, name):
        return getattr(self.handle, name)


def test_a_full_disk_names_the_file_and_keeps_the_last_checkpoint(data_root_64, tmp_path, monkeypatch, capsys):
    """A checkpoint that finds the disk full: the error names checkpoint.pt, the previous checkpoint still loads,
    and no temporary file is left; through the command it is one line and exit 2."""
    import fitting.files
    from fitting.config import load_config
    from fitting.run_folder import prepare_run_dir
    from pipelines.runs.fit import start_run

    config = load_config("tiny", [f"data.data_root={data_root_64}", "data.ratio=1.0", "train.steps=3"])
    run = prepare_run_dir(tmp_path / "run", False)
    trainer = start_run(run, torch.device("cpu"), config, progress=False)
    trainer.train_step()
    trainer.checkpoint()
    trainer.train_step()
    real_fdopen = os.fdopen
    monkeypatch.setattr(fitting.files.os, "fdopen", lambda fd, mode: _FullDisk(real_fdopen(fd, mode)))
    with pytest.raises(OSError) as raised:
        trainer.checkpoint()
    assert raised.value.errno == errno.ENOSPC
    assert _message(raised.value) == f"{run / 'checkpoint.pt'}: No space left on device"
    assert load_checkpoint(run)["step"] == 1
    assert not list(run.glob(".checkpoint*"))
    out = tmp_path / "cli"
    argv = [
        "--config",
        "tiny",
        "--data-root",
        str(data_root_64),
        "--out",
        str(out),
        "--quiet",
        "--set",
        "train.steps=2",
    ]
    assert run_cli("narf-fit", cli_fit.main, argv) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("narf-fit: error: ")]
    assert errors == [f"narf-fit: error: {out / 'config.yaml'}: No space left on device"]  # its first file
    assert not out.exists() or not list(out.rglob(".*.tmp"))


def test_a_full_disk_in_the_view_store_names_its_folder(tmp_path, monkeypatch):
    """The training views' store (``$NARF_CACHE/views``): a write that stops short and then finds the disk full (what
    ``pwrite`` does on Linux: a short count, then ENOSPC on the rest) ends in an error naming the store's folder,
    never a store with a cut record."""
    import numpy as np

    import fitting.view_store

    store = ViewStore(tmp_path / "views")
    image, mask = np.zeros((8, 8, 3), np.uint8), np.zeros((8, 8), bool)
    mask[2:5, 2:5] = True
    store.add(image, mask, mask)
    real_pwrite, calls = os.pwrite, []

    def full_after_a_short_write(fd, data, offset):  # as Linux does: a short count, then the error
        calls.append(len(data))
        if len(calls) == 1:
            return real_pwrite(fd, bytes(data)[: len(data) // 2], offset)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(fitting.view_store.os, "pwrite", full_after_a_short_write)
    with pytest.raises(OSError) as raised:
        store.add(image, mask, mask)
    assert len(calls) == 2 and calls[1] == calls[0] - calls[0] // 2  # the rest was tried where the first stopped
    assert raised.value.errno == errno.ENOSPC and str(tmp_path / "views") in _message(raised.value)
    assert len(store) == 1


def test_one_writer_per_folder(data_root_64, tmp_path, capsys):
    """A second writer of a folder another process holds is refused in one line naming the folder and the holder's
    process id; once the holder is killed (SIGKILL: no chance to clean up) its lock blocks nobody."""
    out = tmp_path / "run"
    code = "import sys, time\nfrom fitting.files import folder_lock\nwith folder_lock(sys.argv[1]):\n"
    code += "    print('locked', flush=True)\n    time.sleep(120)\n"
    holder = spawn.popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        argv = ["--config", "tiny", "--data-root", str(data_root_64), "--out", str(out), "--quiet"]
        assert run_cli("narf-fit", cli_fit.main, [*argv, "--set", "train.steps=2"]) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert lines == [
            f"narf-fit: error: {out}: another command is writing it (process {holder.pid}); wait for it to end"
        ]
        with pytest.raises(FolderBusy, match=f"process {holder.pid}"):
            with folder_lock(out):
                pass
    finally:
        holder.kill()
        holder.wait()
    assert (tmp_path / ".run.lock").exists()  # the killed holder's file is still there ...
    assert run_cli("narf-fit", cli_fit.main, [*argv, "--set", "train.steps=2"]) == 0  # ... and blocks nobody
    assert load_checkpoint(out)["step"] == 2 and not (tmp_path / ".run.lock").exists()


def test_a_replacement_killed_between_its_renames_keeps_the_old_folder(tmp_path, monkeypatch):
    """``publish_folder`` moves the old folder aside, the new one in, then deletes the old one: a kill between the
    two renames leaves the old one aside, and the next writer puts it back before anything else."""
    out, partial = tmp_path / "capture", tmp_path / ".capture.partial"
    out.mkdir()
    (out / "old.txt").write_text("old")
    partial.mkdir()
    (partial / "new.txt").write_text("new")
    real_rename = Path.rename

    def killed(self, target):
        if self == partial:
            raise KeyboardInterrupt  # the process dies here
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", killed)
    with pytest.raises(KeyboardInterrupt):
        publish_folder(partial, out)
    monkeypatch.setattr(Path, "rename", real_rename)
    assert not out.exists()
    restore_replaced(out)
    assert (out / "old.txt").read_text() == "old" and not (tmp_path / ".capture.old").exists()
    publish_folder(partial, out)
    assert sorted(p.name for p in out.iterdir()) == ["new.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capture"]


@pytest.mark.slow
def test_a_prepare_killed_at_random_moments_leaves_the_old_capture_or_the_new(recording, tmp_path):
    """narf-prepare-capture killed at seeded moments after its staging folder appears (tied to that event, not to
    a time since the start, so the first kill lands mid-write on any machine), first while writing a new capture
    (nothing appears), then while replacing it (--overwrite: the old capture stays whole until the new one is
    complete); each time the same command then finishes."""
    rec, out = recording / "rec", tmp_path / "out"
    # a short body fit: what is tested is the writing, which a shorter fit reaches sooner
    short = ["--fit-iterations", "100", "--silhouette-iterations", "50", "--quiet"]
    flags = ["--keypoints", rec / "keypoints", "--masks", rec / "masks", *short]
    argv = _command("prepare_capture", rec, "--out", out, *flags)
    rng, staging = random.Random(1), tmp_path / ".out.partial"
    # killed while it writes the new capture: its staging folder stands, the capture is not there yet
    assert _kill_when(argv, staging.exists, rng.uniform(0.0, 0.5)) is None
    assert not out.exists()
    assert spawn.run(argv, HANG).returncode == 0
    report = (out / "report.json").read_text()
    for _ in range(2):  # killed while it writes the replacement (or, once done, not at all: then it is whole)
        if _kill_when([*argv, "--overwrite"], staging.exists, rng.uniform(0.0, 1.0)) is None:
            assert (out / "report.json").read_text() == report  # the old one, whole
        assert spawn.run([*argv, "--overwrite"], HANG).returncode == 0
        assert json.loads((out / "report.json").read_text())["frames"] == json.loads(report)["frames"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


@pytest.mark.slow
def test_an_eval_killed_at_random_moments_leaves_no_report_that_looks_finished(tiny_run, tmp_path):
    """narf-eval killed three times, each at a seeded moment after it starts writing ``eval/`` (an event, so a loaded
    machine kills it at the same point of its work, and every kill is asserted to have happened), leaves
    ``eval/metrics.json`` absent or whole; the same command then finishes."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run, ignore=shutil.ignore_patterns("eval"))  # the shared run's report is others'
    argv = _command("eval", "--run", run, "--limit", "2", "--quiet")
    rng = random.Random(2)
    for _ in range(3):
        shutil.rmtree(run / "eval", ignore_errors=True)
        assert _kill_when(argv, (run / "eval").exists, rng.uniform(0.0, 0.3)) is None, "narf-eval ended first"
        metrics = run / "eval" / "metrics.json"
        assert not metrics.exists() or json.loads(metrics.read_text())["splits"]
    assert spawn.run(argv, HANG).returncode == 0
    assert json.loads((run / "eval" / "metrics.json").read_text())["splits"]


@pytest.mark.slow
@pytest.mark.parametrize("command", ["synth", "render_video", "export_mesh"])
def test_other_writers_killed_at_random_moments_leave_nothing_half_written(command, tiny_run, tmp_path):
    """narf-synth (a staged folder), narf-render-video and narf-export-mesh (a file written under a hidden name)
    killed twice each, at a seeded moment after their lock, hidden staging folder or temporary file appears (an event,
    not a time since the start: every kill is asserted to land while the command works): their output is absent or
    whole and nothing else visible is left beside it; the same command then finishes and leaves no hidden staging,
    temporary or lock file."""
    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    out = {"synth": tmp_path / "capture", "render_video": tmp_path / "orbit.mp4", "export_mesh": tmp_path / "mesh.ply"}
    argv = {
        "synth": ["--out", out["synth"], "--resolution", "64", "--frames", "6", "--cameras", "4", "--calib-shots", "0"],
        "render_video": ["--run", run, "--kind", "orbit", "--frames", "8", "--out", out["render_video"], "--quiet"],
        "export_mesh": ["--run", run, "--frame", "0", "--resolution", "48", "--out", out["export_mesh"], "--quiet"],
    }[command]
    rng = random.Random(3)
    # the output's lock (taken as the work starts), its staging folder or its temporary file (fitting.files)
    hidden = (f".{out[command].name}.lock", f".{out[command].stem}.partial")

    def writing() -> bool:
        return any(p.name.startswith(hidden) for p in tmp_path.iterdir())

    for _ in range(2):
        assert _kill_when(_command(command, *argv), writing, rng.uniform(0.0, 0.2)) is None, f"{command} ended first"
        assert _absent_or_whole(out[command])
        assert {p.name for p in tmp_path.iterdir() if not p.name.startswith(".")} <= {"run", out[command].name}
    assert spawn.run(_command(command, *argv), HANG).returncode == 0
    assert out[command].exists() and not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]


def _absent_or_whole(target: Path) -> bool:
    """Whether ``target`` is absent, or whole: a capture with its closing ``synthetic.json``, a video whose 8 frames
    all decode, a mesh that loads with faces."""
    if not target.exists():
        return True
    if target.suffix == "":
        return target.is_dir() and (target / "synthetic.json").is_file()
    if target.suffix == ".mp4":
        import imageio.v2 as imageio

        return len(imageio.mimread(target)) == 8
    import trimesh

    return len(trimesh.load(target, force="mesh").faces) > 0


def test_an_image_that_cannot_be_written_is_an_error_naming_it(tmp_path, monkeypatch):
    """cv2.imwrite returns False on a full disk (as on a missing folder): write_image raises an OSError naming the file,
    and every image write of the package goes through it (no module but fitting/files.py calls cv2.imwrite itself;
    the viewer checks its PNG encoding's flag). (Checked against the synthetic writers, plots and the calibration report
    as they were: eight modules listed.)"""
    import re

    import cv2
    import numpy as np

    from fitting.files import write_image

    image = np.zeros((4, 4), np.uint8)
    with pytest.raises(OSError) as caught:
        write_image(tmp_path / "missing" / "mask.png", image)  # no such folder: OpenCV returns False
    assert caught.value.filename == str(tmp_path / "missing" / "mask.png")
    monkeypatch.setattr(cv2, "imwrite", lambda *args: False)  # as a full disk answers
    with pytest.raises(OSError, match="could not be written"):
        write_image(tmp_path / "mask.png", image)
    root = Path(__file__).resolve().parents[1]
    modules = [p for package in ("narf", "fitting", "pipelines") for p in (root / package).rglob("*.py")]
    bare = [p.name for p in modules if re.search(r"cv2\.imwrite\(", p.read_text()) and p.name != "files.py"]
    assert bare == []


def test_a_synthetic_capture_that_fills_the_disk_names_the_file_and_leaves_nothing(tmp_path, monkeypatch, capsys):
    """numpy reports a full disk as an OSError with neither errno nor file name ("20670 requested and 16352
    written"): narf-synth ends with one line naming the file, exit 2, and no staging folder left. (Checked against
    np.save as it was: the line named no file and the hidden .taichi.partial stayed; measured on a 6 MB tmpfs the
    same way.)"""
    import numpy as np

    from pipelines.cli import synth
    from pipelines.cli.common import run_cli

    real_save, calls = np.save, []

    def filling(path, array, **kwargs):
        if isinstance(path, Path):  # files (annots.npy is written through a buffer)
            calls.append(path)
            if len(calls) == 5:
                raise OSError("20670 requested and 16352 written")
        return real_save(path, array, **kwargs)

    monkeypatch.setattr(np, "save", filling)
    args = ["--subject", "taichi", "--data-root", str(tmp_path), "--frames", "4", "--cameras", "2"]
    assert run_cli("narf-synth", synth.main, args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{calls[4]}: a short write" in err[0]
    assert list((tmp_path / "synthetic").iterdir()) == []
