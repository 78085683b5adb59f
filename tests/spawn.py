"""Child processes for tests: default Ctrl-C handling and a bounded wait that fails instead of hanging the suite.

A test run started as a background job (``make test &``), or by a runner that starts its jobs with SIGINT ignored,
passes that disposition on to every process it starts; a command started from such a test would never see the
interrupt an interrupt test sends it, and would train on. ``popen`` and ``run`` give every child the default
SIGINT disposition, so the command installs its own handler, and ``run`` / ``finish`` end in ``pytest.fail``
(the child killed) when a process outlives its timeout.
"""

from __future__ import annotations

import signal
import subprocess
import threading

import pytest


def default_sigint() -> None:
    """``preexec_fn``: restore SIGINT's default disposition in the child, whatever the parent's is."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def popen(argv: list[str], **kwargs) -> subprocess.Popen:
    return subprocess.Popen(argv, preexec_fn=default_sigint, **kwargs)


def run(argv: list[str], timeout: float, **kwargs) -> subprocess.CompletedProcess:
    """``subprocess.run`` with default SIGINT; a child running past ``timeout`` s is killed and fails the test."""
    try:
        return subprocess.run(argv, preexec_fn=default_sigint, timeout=timeout, **kwargs)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{' '.join(map(str, argv[:6]))} ... did not end within {timeout:g} s (killed)")


class Reader:
    """Collects a text pipe on a thread, so a waiting test can look at what came so far and never blocks on it."""

    def __init__(self, pipe):
        self.chunks: list[str] = []
        self.thread = threading.Thread(target=lambda: self.chunks.extend(iter(lambda: pipe.read(1), "")), daemon=True)
        self.thread.start()

    def text(self) -> str:
        return "".join(self.chunks)


def finish(proc: subprocess.Popen, timeout: float, what: str) -> int:
    """Wait for ``proc``; kill it and fail the test if it is still running after ``timeout`` s."""
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        pytest.fail(f"{what}: still running {timeout:g} s after it should have ended (killed)")
