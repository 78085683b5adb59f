"""Shared CLI plumbing: known errors become one clear line and a non-zero exit code, never a traceback
(set ``NARF_DEBUG=1`` to see the traceback)."""

from __future__ import annotations

import argparse
import contextvars
import ctypes
import functools
import math
import os
import sys
from collections.abc import Callable

from pipelines.datasets.errors import CaptureError
from pipelines.datasets.smpl_files import SmplFileError


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows an option's default unless it is None, False or already named in the help text."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        hidden = action.default is None or action.default is False or action.default == argparse.SUPPRESS
        if hidden or "default" in text:
            return text
        return super()._get_help_string(action)


def positive_number(text: str) -> float:
    """argparse type: a finite number > 0 (``nan``, ``inf``, 0 and negatives are usage errors)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got '{text}'") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got '{text}'")
    return value


def add_motion_fps(parser: argparse.ArgumentParser, applies_to: str = "--motion") -> None:
    """``--motion-fps``: the frame rate of a motion file that records none (ZJU params folders play at 30)."""
    parser.add_argument(
        "--motion-fps",
        type=positive_number,
        default=None,
        help=f"{applies_to}: its frame rate when the file has none (ZJU: 30)",
    )


def add_samples(parser: argparse.ArgumentParser, recorded: str = "") -> None:
    """``--samples COARSE FINE``: a subject run's renders with other samples a ray than its ``render.eval_*``
    (docs/model.md §7); ``recorded`` says where the counts are written down. Checked by :func:`samples_of`."""
    parser.add_argument(
        "--samples",
        nargs=2,
        type=int,
        default=None,
        metavar=("COARSE", "FINE"),
        help="subject runs: render with COARSE coarse and FINE importance samples a ray in place of the run's "
        f"render.eval_coarse / eval_fine (the CPU preset 16 16, the paper 64 128){recorded}. Default: the run's",
    )


def samples_of(args: argparse.Namespace) -> tuple[int, int] | None:
    """The counts of :func:`add_samples`, or None; ValueError (one line) for counts no render takes."""
    if args.samples is None:
        return None
    coarse, fine = args.samples
    if coarse < 2 or fine < 0:
        raise ValueError(f"--samples {coarse} {fine}: COARSE must be >= 2 and FINE >= 0")
    return coarse, fine


def add_smpl_dir(parser: argparse.ArgumentParser) -> None:
    """``--smpl-dir`` of a command that loads a run (:func:`use_smpl_dir`)."""
    parser.add_argument(
        "--smpl-dir",
        default=None,
        help="where the run's body model now is, when it has moved (checked against the hash the run recorded)",
    )


def own_context(main: Callable) -> Callable:
    """Decorator of a command's ``main``: it runs in a copy of the caller's context, so the choices it makes there
    (``--smpl-dir``: :func:`use_smpl_dir`) end with it, also when a caller runs ``main`` directly."""

    @functools.wraps(main)
    def in_own_context(*args, **kwargs):
        return contextvars.copy_context().run(main, *args, **kwargs)

    return in_own_context


def use_smpl_dir(path: str | None) -> None:
    """A command's ``--smpl-dir``: the default SMPL model of this command's calls (its ``main`` runs in a context of
    its own, :func:`own_context`, so nothing outlives it), where a run's recorded body model is also looked for (the
    run's recorded hash decides whether it is the same file: docs/guides/fitting.md)."""
    from pipelines.body.locate import choose_smpl_dir

    if path:
        if not os.path.exists(path):
            raise FileNotFoundError(f"{path}: no such SMPL model file or folder (--smpl-dir)")
        choose_smpl_dir(path)


def at_least(minimum: int, at_most: int | None = None) -> Callable[[str], int]:
    """argparse type: a whole number >= ``minimum`` (and <= ``at_most`` when given)."""
    wanted = f">= {minimum}" if at_most is None else f"in [{minimum}, {at_most}]"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number {wanted}, got '{text}'") from None
        if value < minimum or (at_most is not None and value > at_most):
            raise argparse.ArgumentTypeError(f"expected a whole number {wanted}, got '{text}'")
        return value

    return parse


KNOWN_ERRORS = (
    CaptureError,
    SmplFileError,
    ValueError,
    RuntimeError,
    IsADirectoryError,
    FileExistsError,
    FileNotFoundError,
    NotADirectoryError,
    PermissionError,
    KeyError,
)


#: glibc mallopt parameters and the values set by :func:`keep_freed_memory` (docs/design.md, "Memory allocator")
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD_BYTES, TRIM_THRESHOLD_BYTES = 32 << 20, 1 << 30


def keep_freed_memory() -> bool:
    """Let glibc's malloc keep freed blocks of up to 32 MiB for reuse instead of handing them back to the kernel.

    A training step allocates and frees hundreds of activation tensors of a few MiB whose sizes change from step to
    step; by default glibc serves each from a fresh mmap, so every step pays about 10^4 page faults (docs/design.md,
    "Memory allocator"). Does nothing (returns False) off glibc, or when the user set ``MALLOC_MMAP_THRESHOLD_`` or
    ``MALLOC_TRIM_THRESHOLD_`` (glibc's own switches, which then win) or preloads another allocator.
    """
    user_set = any(k in os.environ for k in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "LD_PRELOAD"))
    if user_set or not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # musl and other C libraries
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )


#: libgomp's busy-wait, in spins, before an idle OpenMP worker sleeps, set by :func:`short_openmp_wait` (its own
#: default is 300,000; docs/design.md, "OpenMP workers' wait")
OPENMP_SPIN_COUNT = "10000"


def short_openmp_wait() -> bool:
    """Let torch's idle OpenMP workers (libgomp) sleep after 10,000 spins instead of 300,000: ``GOMP_SPINCOUNT``.

    libgomp reads it once, when torch loads it, so this has to run before ``import torch``; it returns False, setting
    nothing, once torch is imported, or when the user set ``GOMP_SPINCOUNT`` or ``OMP_WAIT_POLICY`` (theirs win).
    Other OpenMP runtimes (LLVM's libomp on macOS) ignore the variable. A training step's hundreds of small operators
    leave gaps shorter than the default spin, so the worker never rests and the calling thread computed its part
    slower on the 2-core machine (docs/design.md, "OpenMP workers' wait").
    """
    if "torch" in sys.modules or any(k in os.environ for k in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")):
        return False
    os.environ["GOMP_SPINCOUNT"] = OPENMP_SPIN_COUNT
    return True


def flush_subnormals() -> bool:
    """Treat float32 values below 1.2e-38 as 0 on the CPU (flush-to-zero and denormals-are-zero), in this thread and in
    every CPU worker thread started after it; returns False where torch has no such mode for the CPU.

    The mode is a per-thread register that a new thread copies from the thread that starts it, and torch starts its
    worker threads at the first parallel operation; set later, it reaches the calling thread only and the workers
    keep computing on subnormals at a fraction of the speed (docs/design.md, "Subnormal numbers").
    """
    import torch

    return torch.set_flush_denormal(True)


def attach_dash_values(argv: list[str] | None, flags: tuple[str, ...]) -> list[str]:
    """``argv`` (None: ``sys.argv[1:]``) with ``FLAG -5:3`` written ``FLAG=-5:3`` for each of ``flags``, so that a
    range value starting with a minus reaches the flag's own check, not argparse's 'expected one argument'."""
    argv = list(sys.argv[1:] if argv is None else argv)
    out, i = [], 0
    while i < len(argv):
        if argv[i] in flags and i + 1 < len(argv) and argv[i + 1].startswith("-") and argv[i + 1][1:2].isdigit():
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
            continue
        out.append(argv[i])
        i += 1
    return out


def run_cli(prog: str, main: Callable[[list[str] | None], int | None], argv: list[str] | None = None) -> int:
    """Run ``main(argv)``; print ``prog: error: ...`` and return 2 on a known error, 130 on Ctrl-C. The allocator
    keeps freed memory for reuse (:func:`keep_freed_memory`), idle OpenMP workers sleep sooner
    (:func:`short_openmp_wait`) and subnormal floats are flushed in every CPU thread (:func:`flush_subnormals`), all
    set before ``main`` does any work; ``--help`` does none, and answers without importing torch."""
    keep_freed_memory()
    waiting = short_openmp_wait()
    if not {"-h", "--help"} & set(sys.argv[1:] if argv is None else argv):
        flush_subnormals()
    try:
        # a context of its own: the command's choices (--smpl-dir) end with it, also for an in-process caller
        return int(contextvars.copy_context().run(main, argv) or 0)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except (*KNOWN_ERRORS, OSError) as err:
        if os.environ.get("NARF_DEBUG"):
            raise
        print(f"{prog}: error: {_message(err)}", file=sys.stderr)
        return 2
    finally:
        # libgomp read the variable when torch loaded it (at the latest in main): an in-process caller gets its
        # environment back as it was, and so do the processes it starts later
        if waiting:
            os.environ.pop("GOMP_SPINCOUNT", None)


def _message(err: Exception) -> str:
    """One line: a KeyError's key text, an OSError's file and reason (``[Errno 28] ...: 'path'`` otherwise)."""
    if isinstance(err, KeyError) and err.args:
        return str(err.args[0])
    if isinstance(err, OSError) and err.strerror and err.filename:
        return f"{err.filename}: {err.strerror}"
    return str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
