"""Shared CLI plumbing: known errors become one clear line and a non-zero exit code, never a traceback
(set ``NARF_DEBUG=1`` to see the traceback)."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

from pipelines.smpl_files import SmplFileError
from pipelines.zju_mocap import CaptureError

KNOWN_ERRORS = (CaptureError, SmplFileError, ValueError, RuntimeError, IsADirectoryError, FileExistsError,
                FileNotFoundError, NotADirectoryError, PermissionError, KeyError)  # fmt: skip


def run_cli(prog: str, main: Callable[[list[str] | None], int | None], argv: list[str] | None = None) -> int:
    """Run ``main(argv)``; print ``prog: error: ...`` and return 2 on a known error, 130 on Ctrl-C."""
    try:
        return int(main(argv) or 0)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except KNOWN_ERRORS as err:
        if os.environ.get("NARF_DEBUG"):
            raise
        message = err.args[0] if isinstance(err, KeyError) and err.args else err
        print(f"{prog}: error: {message}", file=sys.stderr)
        return 2
