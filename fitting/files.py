"""File safety, in one place: every file and folder the tools write appears whole or not at all.

* A file is written to a hidden temporary file beside it (same folder, so same file system) and renamed onto its
  name (``os.replace`` is atomic on POSIX and Windows): :func:`atomic_write_bytes`, or :func:`atomic_output` for
  writers that want a file name (videos, ``.mat`` files).
* A folder of many files is built in a hidden ``.<name>.partial`` folder beside it and moved into place when it is
  complete (:func:`staged_folder`), so an interrupted run never leaves output that looks finished. An older folder
  of that name is moved aside first and deleted last (:func:`publish_folder`).
* A write that fails (a full disk) names the file it was writing (:func:`named_errors`), and leaves no temporary file.
* One process writes a run or capture folder at a time (:func:`folder_lock`).

This is the only module that renames output into place (docs/design.md, "Files")."""

from __future__ import annotations

import contextlib
import errno
import functools
import inspect
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
    with named_errors(path):
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


@contextlib.contextmanager
def named_errors(path: Path) -> Iterator[None]:
    """An OSError raised in the block without a file name (a write to an open file that finds the disk full:
    ``[Errno 28] No space left on device``) gets ``path``'s, so the one-line error says which file it was."""
    try:
        yield
    except OSError as err:
        if err.filename is not None or err.errno is None:
            raise
        raise OSError(err.errno, err.strerror, str(path)) from err


def write_image(path: Path, image, params: tuple[int, ...] = ()) -> None:
    """``cv2.imwrite`` that raises: OpenCV returns False where Python raises (a full disk, a missing folder, an
    unknown extension), which would leave a missing or partial image behind a finished-looking output. The OSError
    names the file, as the fit's write errors do."""
    import cv2

    if not cv2.imwrite(str(path), image, list(params)):
        raise OSError(
            errno.EIO, "the image could not be written (disk full, folder missing or unknown format)", str(path)
        )


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
    restore_replaced(out)
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
    an empty one). The older one is moved aside (``.<name>.old``) first and deleted only once the new one is in
    place, so a kill at any moment leaves the old folder or the new one: a kill between the two renames leaves the old
    one aside, and the next writer of ``out`` puts it back (:func:`restore_replaced`)."""
    out = Path(out)
    restore_replaced(out)
    old = _aside(out)
    if out.exists():
        if replace:
            out.rename(old)
        else:
            out.rmdir()
    Path(partial).rename(out)
    shutil.rmtree(old, ignore_errors=True)
    return out


def _aside(out: Path) -> Path:
    return out.parent / f".{out.name}.old"


def restore_replaced(out: Path) -> None:
    """Undo a :func:`publish_folder` killed halfway: an old folder moved aside with no new one in its place goes back
    to ``out``; one left beside a complete ``out`` (killed while deleting it) is deleted."""
    out, old = Path(out), _aside(Path(out))
    if not old.exists():
        return
    if out.exists():
        shutil.rmtree(old, ignore_errors=True)
    else:
        old.rename(out)


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


class FolderBusy(OSError):
    """Another process writes the folder (:func:`folder_lock`)."""


@contextlib.contextmanager
def folder_lock(folder: Path) -> Iterator[None]:
    """Hold the write lock of ``folder`` for the block: one writer per run or capture folder.

    The lock is an advisory ``flock`` on a hidden ``.<name>.lock`` file beside the folder (beside, so that it
    outlives the folder being replaced), which holds the owner's process id. The kernel drops it when its process
    ends, however it ends, so a lock left by a killed process blocks nobody. The file is removed on release; a
    process that locked a file which was removed meanwhile tries again on the new one. Where ``flock`` does not
    exist (Windows) the block runs unlocked.

    Raises:
        FolderBusy: another live process holds the lock (the message names the folder and its process id).
    """
    try:
        import fcntl
    except ImportError:  # no flock on this system
        yield
        return
    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    lock = folder.parent / f".{folder.name}.lock"
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666 & ~_UMASK)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
            os.close(fd)
            raise FolderBusy(
                f"{folder}: another command is writing it (process {holder}); wait for it to end"
            ) from None
        if _same_file(fd, lock):
            break
        os.close(fd)  # the holder removed the file as we opened it: lock the one there now
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        Path(lock).unlink(missing_ok=True)
        os.close(fd)


def _same_file(fd: int, path: Path) -> bool:
    """Whether the open file ``fd`` is still the file at ``path``."""
    try:
        return os.path.samestat(os.fstat(fd), os.stat(path))
    except FileNotFoundError:
        return False


def writes_folder(argument: str = "out"):
    """Decorator: the function holds :func:`folder_lock` on the folder its argument ``argument`` names while it
    runs."""

    def wrap(function):
        signature = inspect.signature(function)

        @functools.wraps(function)
        def locked(*args, **kwargs):
            folder = signature.bind(*args, **kwargs).arguments[argument]
            with folder_lock(Path(folder)):
                return function(*args, **kwargs)

        return locked

    return wrap
