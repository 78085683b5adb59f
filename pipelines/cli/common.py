"""Shared CLI plumbing: known errors become one clear line and a non-zero exit code, never a traceback
(set ``NARF_DEBUG=1`` to see the traceback)."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable

from pipelines.datasets.smpl_files import SmplFileError
from pipelines.datasets.zju_mocap import CaptureError


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows an option's default unless it is None, False or already named in the help text."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        hidden = action.default is None or action.default is False or action.default == argparse.SUPPRESS
        if hidden or "default" in text:
            return text
        return super()._get_help_string(action)


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


def run_cli(prog: str, main: Callable[[list[str] | None], int | None], argv: list[str] | None = None) -> int:
    """Run ``main(argv)``; print ``prog: error: ...`` and return 2 on a known error, 130 on Ctrl-C."""
    try:
        return int(main(argv) or 0)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except (*KNOWN_ERRORS, OSError) as err:
        if os.environ.get("NARF_DEBUG"):
            raise
        print(f"{prog}: error: {_message(err)}", file=sys.stderr)
        return 2


def _message(err: Exception) -> str:
    """One line: a KeyError's key text, an OSError's file and reason (``[Errno 28] ...: 'path'`` otherwise)."""
    if isinstance(err, KeyError) and err.args:
        return str(err.args[0])
    if isinstance(err, OSError) and err.strerror and err.filename:
        return f"{err.filename}: {err.strerror}"
    return str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
