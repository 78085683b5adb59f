"""Helpers of the bad-input tests (tests/test_bad_input_*.py, one file per command): run a command in-process and
expect one ``narf-xxx: error:`` line and exit code 2, damage a capture, interrupt a command."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import spawn

from pipelines.cli import (
    calibrate,
    convert_smpl,
    export_mesh,
    fit,
    prepare_capture,
    prepare_thuman,
    render_video,
    synth,
)
from pipelines.cli import eval as cli_eval
from pipelines.cli.common import run_cli

ROOT = Path(__file__).resolve().parents[1]


MAINS = {
    "narf-synth": synth.main,
    "narf-fit": fit.main,
    "narf-eval": cli_eval.main,
    "narf-render-video": render_video.main,
    "narf-export-mesh": export_mesh.main,
    "narf-calibrate": calibrate.main,
    "narf-convert-smpl": convert_smpl.main,
    "narf-prepare-thuman": prepare_thuman.main,
}


def expect_usage_error(capsys, prog: str, argv: list[str], message: str) -> str:
    """A flag out of its range is argparse's usage error: exit code 2, the usage line and one error line."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        MAINS[prog]([str(a) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and err[-1].startswith(f"{prog}: error: ") and message in err[-1], err
    return err[-1]


def expect_error(capsys, prog: str, argv: list[str], message: str) -> str:
    """Run a command in-process: exit code 2 and exactly one stderr line naming the problem."""
    capsys.readouterr()
    assert run_cli(prog, MAINS[prog], [str(a) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and err[-1].startswith(f"{prog}: error: "), err
    lines = [line for line in err if line.startswith(f"{prog}: error: ")]  # besides notices and progress bars
    assert len(lines) == 1 and "Traceback" not in "\n".join(err), err
    assert message in lines[0], (message, lines[0])
    return lines[0]


def _fit_args(root, out):
    return ["--config", "tiny", "--data-root", root, "--set", "data.ratio=1.0", "--set", "train.steps=1", "--out", out]


def _annots(root):
    path = root / "synthetic" / "taichi" / "annots.npy"
    return path, np.load(path, allow_pickle=True).item()


def _save_annots(path, annots):
    np.save(path, np.array(annots, dtype=object), allow_pickle=True)


def _interrupt_after(argv: list[str], ready, timeout: float = 240.0) -> subprocess.CompletedProcess:
    """Start a command (SIGINT at its default, whatever this test run inherited), send SIGINT once ``ready(stderr so
    far)`` holds, and wait for it to end; a command that has not ended 120 s after the interrupt fails the test."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = spawn.popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    out, err = spawn.Reader(proc.stdout), spawn.Reader(proc.stderr)
    deadline = time.time() + timeout
    while not ready(err.text()) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    spawn.finish(proc, 120, f"{' '.join(argv[2:4])} after Ctrl-C")
    out.thread.join(timeout=10)
    err.thread.join(timeout=10)
    return subprocess.CompletedProcess(argv, proc.returncode, out.text(), err.text())


def _cli(name: str) -> list[str]:
    return [sys.executable, "-c", f"from pipelines.cli.{name} import entrypoint; entrypoint()"]


def prepare_error(capsys, argv) -> str:
    """narf-prepare-capture in-process: exit code 2 and exactly one error line, returned."""
    capsys.readouterr()
    assert run_cli("narf-prepare-capture", prepare_capture.main, [str(a) for a in argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("narf-prepare-capture: error: "), err
    return err[0]
