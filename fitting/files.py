"""File safety, in one place: every file and folder the tools write appears whole or not at all.

* A file is written to a hidden temporary file beside it (same folder, so same file system) and renamed onto its
  name (``os.replace`` is atomic on POSIX and Windows): :func:`atomic_write_bytes`, or :func:`atomic_output` for
  writers that want a file name (videos, ``.mat`` files).
* A folder of many files is built in a hidden ``.<name>.partial`` folder beside it and moved into place when it is
  complete (:func:`staged_folder`), so an interrupted run never leaves output that looks finished.

This is the only module that renames output into place (docs/design.md, "Files")."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _umask() -> int:
    """The process's umask (read by setting it, so once, at import, before any thread writes)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _umask()


def atomic_write_bytes(path: Path, data: bytes, sync: bool = False) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename (``sync``: flushed to
    the disk first, for files a crash must not lose). The file gets the permissions of any new file (0666 less the
    umask), not the 0600 of the temporary file. A kill mid-write leaves the old file and a hidden
    ``.<name>.*.tmp`` (:func:`remove_stale`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            if sync:
                handle.flush()
                os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def remove_stale(path: Path) -> None:
    """Remove the temporary files that writers of ``path`` killed mid-write left behind (one writer per file)."""
    path = Path(path)
    for stale in path.parent.glob(f".{path.stem}.*.tmp"):
        stale.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_output(path: Path) -> Iterator[Path]:
    """A hidden file name beside ``path`` with its suffix (``.<stem>.partial<suffix>``), for writers that take a
    name; renamed onto ``path`` when the block ends without error, removed in every case otherwise."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.partial{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def fresh_partial(out: Path) -> Path:
    """The hidden staging folder of ``out``, ``.<name>.partial`` beside it, created empty (what an interrupted run
    left there is cleared)."""
    out = Path(out)
    partial = out.parent / f".{out.name}.partial"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    return partial


@contextlib.contextmanager
def staged_folder(out: Path, replace: bool = True) -> Iterator[Path]:
    """Build the folder ``out`` in a fresh staging folder (:func:`fresh_partial`) and move it
    into place when the block ends without error, replacing an older ``out`` (``replace=False``: ``out`` must be
    absent or an empty folder). On an error or Ctrl-C the staging folder is removed and ``out`` is left as it was."""
    out = Path(out)
    partial = fresh_partial(out)
    try:
        yield partial
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    publish_folder(partial, out, replace)


def publish_folder(partial: Path, out: Path, replace: bool = True) -> Path:
    """Move the finished staging folder ``partial`` onto ``out``, replacing an older ``out`` (``replace=False``: only
    an empty one)."""
    out = Path(out)
    if out.exists():
        if replace:
            shutil.rmtree(out)
        else:
            out.rmdir()
    Path(partial).rename(out)
    return out


def atomic_write_text(path: Path, text: str) -> None:
    """:func:`atomic_write_bytes` of ``text`` in UTF-8."""
    atomic_write_bytes(path, text.encode("utf-8"))


def merge_folder(partial: Path, out: Path) -> Path:
    """Move every entry of the finished staging folder ``partial`` into the folder ``out`` (created if missing),
    each replacing the entry of its name; other entries of ``out`` stay. Removes ``partial``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for path in Path(partial).iterdir():
        if path.is_dir() and (out / path.name).is_dir():
            shutil.rmtree(out / path.name)
        path.replace(out / path.name)
    Path(partial).rmdir()
    return out
