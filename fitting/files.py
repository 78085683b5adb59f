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
import glob
import inspect
import itertools
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path


@functools.cache
def _umask() -> int:
    """The process's umask, read once, on first use: from ``/proc/self/status`` where Linux gives it (nothing
    changes), else by setting it and putting it back (the only portable way, which for that instant changes it for
    every thread of the process)."""
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def new_file_mode() -> int:
    """The permissions a new file gets (0666 less the umask)."""
    return 0o666 & ~_umask()


#: the errors with which a file system says that a folder cannot be flushed at all (EINVAL: some network and
#: virtual file systems; ENOTSUP / EOPNOTSUPP / EBADF: others): like SQLite and git there, carry on
UNSYNCABLE_FOLDER = {errno.EINVAL, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EBADF}
_told_unsyncable: set[str] = set()


def sync_folder(folder: Path) -> None:
    """Flush ``folder``'s entries (the renames into it) to the disk, so that a power loss after a rename that
    publishes cannot undo it. A no-op where folders cannot be opened (Windows), and, said once a file system on
    standard error, where the file system cannot flush a folder (:data:`UNSYNCABLE_FOLDER`): the rename is in place
    and stays, only its durability across a power loss is the file system's."""
    flags = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0)
    try:
        fd = os.open(folder, flags)
    except (PermissionError, IsADirectoryError):  # Windows: folders are not files
        return
    try:
        os.fsync(fd)
    except OSError as err:
        if err.errno not in UNSYNCABLE_FOLDER:
            raise
        device = str(os.fstat(fd).st_dev)
        if device not in _told_unsyncable:
            _told_unsyncable.add(device)
            print(
                f"note: {folder}: this file system cannot flush folders ({err.strerror}); carrying on", file=sys.stderr
            )
    finally:
        os.close(fd)


#: a tree of more files than this is flushed by one ``sync()`` of the whole system rather than file by file
SYNC_TREE_FILES = 64


def sync_tree(folder: Path) -> None:
    """Flush every file and folder under ``folder`` (before it is renamed into place: its files' data must reach
    the disk before the rename does). A small tree file by file; a large one (a capture's 10^4-10^5 images) by one
    ``os.sync()``, which on Linux returns once every file system's dirty data is on the disk: the same guarantee in
    one call, where an ``fsync`` a file waits for the disk once per file. Where ``os.sync`` does not exist (Windows),
    file by file."""
    walked = list(os.walk(folder))
    if hasattr(os, "sync") and sum(len(files) for _, _, files in walked) > SYNC_TREE_FILES:
        os.sync()
        return
    for root, _, files in walked:
        for name in files:
            sync_file(Path(root) / name)
        sync_folder(Path(root))


def sync_file(path: Path) -> None:
    """Flush the file ``path``'s data to the disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes, sync: bool = False) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename (``sync``: the file
    flushed to the disk before the rename and the folder after it, for files a power loss must not lose). The file
    gets the permissions of any new file (0666 less the
    umask), not the 0600 of the temporary file. A kill mid-write leaves the old file and a hidden
    ``.<name>.*.tmp`` (:func:`remove_stale`)."""
    path = Path(path)
    with named_errors(path):
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        try:
            os.fchmod(fd, new_file_mode())
            with os.fdopen(fd, "wb") as handle:
                handle.write(data)
                if sync:
                    handle.flush()
                    os.fsync(handle.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        if sync:
            sync_folder(path.parent)


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


def write_npy(path: Path, array, allow_pickle: bool = False) -> None:
    """``np.save`` whose errors name the file: numpy reports a short write (a full disk) as an OSError with neither
    errno nor file name ("20670 requested and 16352 written"), which becomes an EIO naming ``path``. Objects are
    pickled only where the format demands it (``allow_pickle``)."""
    import numpy as np

    try:
        np.save(path, array, allow_pickle=allow_pickle)
    except OSError as err:
        if err.filename is not None:
            raise
        reason = err.strerror or f"a short write ({err}): is the disk full?"
        raise OSError(err.errno or errno.EIO, reason, str(path)) from err


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


_OUTPUTS = itertools.count()


def remove_orphaned_partials(path: Path) -> None:
    """Remove the temporary files of :func:`atomic_output` for ``path`` whose writer no longer runs (killed
    mid-write: ``.<stem>.partial-<process id>-<n><suffix>`` of a process id that is gone); a live writer's stay."""
    path = Path(path)
    pattern = f"{glob.escape(f'.{path.stem}.partial-')}*-*{glob.escape(path.suffix)}"
    for partial in path.parent.glob(pattern):
        writer = partial.name[len(f".{path.stem}.partial-") :].split("-", 1)[0]
        if writer.isdigit() and not _process_runs(int(writer)):
            partial.unlink(missing_ok=True)


def _process_runs(pid: int) -> bool:
    """Whether a process ``pid`` exists (another user's counts: signal 0 is refused, not unanswered)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


@contextlib.contextmanager
def atomic_output(path: Path) -> Iterator[Path]:
    """A hidden file name beside ``path`` with its suffix (``.<stem>.partial-<process id>-<n><suffix>``, one per
    writer, so two writers of one file never write the same temporary file), for writers that take a name; renamed
    onto ``path`` when the block ends without error, removed in every case otherwise."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_orphaned_partials(path)
    tmp = path.with_name(f".{path.stem}.partial-{os.getpid()}-{next(_OUTPUTS)}{path.suffix}")
    try:
        yield tmp
        sync_file(tmp)  # the data on the disk before the rename, and the rename flushed after it (module docstring)
        os.replace(tmp, path)
        sync_folder(path.parent)
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
    one aside, and the next writer of ``out`` puts it back (:func:`restore_replaced`). The old folder is renamed to a
    trash name before it is deleted, so a kill while deleting it leaves a half-deleted folder that is never restored.
    The new folder's files are flushed to the disk before the rename, and the rename before the old one is deleted:
    a power loss cannot leave a published folder of empty files in place of the old one."""
    out = Path(out)
    restore_replaced(out)
    old = _aside(out)
    sync_tree(Path(partial))
    if out.exists():
        if replace:
            out.rename(old)
        else:
            out.rmdir()
    Path(partial).rename(out)
    sync_folder(out.parent)
    _delete(old)
    return out


def _aside(out: Path) -> Path:
    return out.parent / f".{out.name}.old"


def _delete(folder: Path) -> None:
    """Delete ``folder`` (if there) by renaming it to a trash name first (``.<name>.trash-<process id>``), so that
    no name that :func:`restore_replaced` reads ever holds a half-deleted folder."""
    if not folder.exists():
        return
    trash = folder.with_name(f"{folder.name}.trash-{os.getpid()}")
    if trash.exists():  # this process's own, killed earlier
        shutil.rmtree(trash, ignore_errors=True)
    folder.rename(trash)
    if trash.is_dir():
        shutil.rmtree(trash, ignore_errors=True)
    else:  # a file that stood where a folder is published
        trash.unlink(missing_ok=True)


def restore_replaced(out: Path) -> None:
    """Undo a :func:`publish_folder` killed halfway: an old folder moved aside with no new one in its place goes back
    to ``out``; one left beside a complete ``out`` is deleted, as are trash folders whose deletion was killed."""
    out, old = Path(out), _aside(Path(out))
    for trash in out.parent.glob(f".{glob.escape(out.name)}.old.trash-*"):
        shutil.rmtree(trash, ignore_errors=True)
    if not old.exists():
        return
    if out.exists():
        _delete(old)
    else:
        old.rename(out)
        sync_folder(out.parent)


def atomic_write_text(path: Path, text: str) -> None:
    """:func:`atomic_write_bytes` of ``text`` in UTF-8."""
    atomic_write_bytes(path, text.encode("utf-8"))


def restore_merged(out: Path) -> None:
    """Undo :func:`merge_folder`s killed halfway in ``out``: each sub-folder moved aside (``.<name>.old``) goes back
    or is deleted as :func:`restore_replaced` says. Commands that merge into ``out`` call it before their work."""
    out = Path(out)
    if not out.is_dir():
        return
    for old in out.glob(".*.old"):
        if old.is_dir():
            restore_replaced(out / old.name[1 : -len(".old")])


def merge_folder(partial: Path, out: Path) -> Path:
    """Move every entry of the finished staging folder ``partial`` into the folder ``out`` (created if missing),
    each replacing the entry of its name; other entries of ``out`` stay. Removes ``partial``. A file is renamed onto
    its name; a folder is published as :func:`publish_folder` does (the old one moved aside, then deleted), so a kill
    at any moment leaves each entry old or new, never missing."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for path in Path(partial).iterdir():
        if path.is_dir():
            publish_folder(path, out / path.name)
        else:
            sync_file(path)
            path.replace(out / path.name)
    sync_folder(out)
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

    The lock is keyed by the folder's resolved path, so a path through a symbolic link takes the same lock. A lock
    file that this user may not write (left by another user) is locked read-only (``flock`` allows it) and its
    process id is not written.

    Raises:
        FolderBusy: another live process holds the lock (the message names the folder and its process id).
        OSError: the lock file cannot be created (a read-only folder), naming it.
    """
    try:
        import fcntl
    except ImportError:  # no flock on this system
        yield
        return
    folder = Path(folder).resolve()
    with named_errors(folder.parent):
        folder.parent.mkdir(parents=True, exist_ok=True)
    lock = folder.parent / f".{folder.name}.lock"
    while True:
        fd, writable = _open_lock(lock)
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
        if writable:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        with contextlib.suppress(PermissionError):  # another user's lock file in a folder we may not write
            Path(lock).unlink(missing_ok=True)
        os.close(fd)


def _open_lock(lock: Path) -> tuple[int, bool]:
    """The lock file opened for ``flock``, and whether it could be opened for writing (a file of another user's may
    only be readable). An OSError names the lock file (a folder where nothing may be created)."""
    try:
        return os.open(lock, os.O_RDWR | os.O_CREAT, new_file_mode()), True
    except PermissionError:
        if not lock.exists():
            raise OSError(errno.EACCES, "cannot create the lock file (the folder is not writable)", str(lock)) from None
        with named_errors(lock):
            return os.open(lock, os.O_RDONLY), False


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
