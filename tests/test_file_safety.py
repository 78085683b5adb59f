"""File safety (fitting.files, docs/results/faults.md): folders replaced or merged by renames survive a kill at any
rename whole, old or new; what publishes is flushed to the disk, folder included; locks are keyed by the real
path, work on another user's lock file and fail in one line where no lock file can be made. Each test says which
change to the code it was checked against (the test fails on the code without the fix)."""

import errno
import os
import shutil
from pathlib import Path

import pytest

from fitting import files
from fitting.files import (
    FolderBusy,
    atomic_output,
    atomic_write_bytes,
    folder_lock,
    merge_folder,
    publish_folder,
    restore_replaced,
)
from pipelines.cli.common import _message


def _folder(path: Path, text: str, n: int = 3) -> Path:
    path.mkdir(parents=True)
    for i in range(n):
        (path / f"{i}.txt").write_text(text)
    return path


def _contents(path: Path) -> set[str]:
    return {p.read_text() for p in path.iterdir()}


def test_a_half_deleted_old_folder_is_never_restored(tmp_path, monkeypatch):
    """A kill while the replaced folder is deleted leaves it half-deleted; if the user then removes the new folder,
    the next writer must not put the half-deleted one back. (Checked against deleting ``.X.old`` in place, without
    the rename to a trash name: the test fails.)"""
    out = _folder(tmp_path / "capture", "old")
    partial = _folder(tmp_path / ".capture.partial", "new")
    real_rmtree = shutil.rmtree

    def killed_midway(path, *args, **kwargs):  # one file gone, then the process dies
        next(Path(path).iterdir()).unlink()
        raise KeyboardInterrupt

    monkeypatch.setattr(files.shutil, "rmtree", killed_midway)
    with pytest.raises(KeyboardInterrupt):
        publish_folder(partial, out)
    monkeypatch.setattr(files.shutil, "rmtree", real_rmtree)
    assert _contents(out) == {"new"}
    real_rmtree(out)  # the user removes the new capture
    restore_replaced(out)
    assert not out.exists()  # nothing half-deleted comes back ...
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # ... and the trash is gone


@pytest.mark.parametrize("kill_at", range(1, 6))
def test_a_merge_killed_at_any_rename_keeps_every_entry_old_or_new(tmp_path, monkeypatch, kill_at):
    """``merge_folder`` (narf-calibrate's output) replaces a sub-folder by renames only: a kill at the n-th rename
    leaves ``colmap/`` whole, old or new, once the next writer has restored it (``restore_replaced``); the file
    beside it is old or new. (Checked against the old ``rmtree`` then rename: a kill at the rename lost the
    folder.)"""
    out = tmp_path / "calib"
    _folder(out / "colmap", "old")
    (out / "report.json").write_text("old")
    partial = tmp_path / ".calib.partial"
    _folder(partial / "colmap", "new")
    (partial / "report.json").write_text("new")
    calls = {"n": 0}
    real_rename, real_replace = Path.rename, Path.replace

    def counted(real):
        def rename(self, target):
            calls["n"] += 1
            if calls["n"] == kill_at:
                raise KeyboardInterrupt
            return real(self, target)

        return rename

    monkeypatch.setattr(Path, "rename", counted(real_rename))
    monkeypatch.setattr(Path, "replace", counted(real_replace))
    try:
        merge_folder(partial, out)
    except KeyboardInterrupt:
        pass
    monkeypatch.setattr(Path, "rename", real_rename)
    monkeypatch.setattr(Path, "replace", real_replace)
    restore_replaced(out / "colmap")
    assert _contents(out / "colmap") in ({"old"}, {"new"})
    assert (out / "report.json").read_text() in ("old", "new")


def _synced_paths(monkeypatch) -> list[str]:
    """Record the path of every file or folder ``os.fsync`` flushes (Linux: /proc/self/fd)."""
    if not Path("/proc/self/fd").is_dir():
        pytest.skip("needs /proc/self/fd to name the flushed files")
    synced, real_fsync = [], os.fsync

    def record(fd):
        synced.append(os.readlink(f"/proc/self/fd/{fd}"))
        return real_fsync(fd)

    monkeypatch.setattr(files.os, "fsync", record)
    return synced


def test_a_synced_write_flushes_its_folder_after_the_rename(tmp_path, monkeypatch):
    """``atomic_write_bytes(sync=True)`` (checkpoints) flushes the file, then its folder, so that the rename
    survives a power loss. (Checked against the file-only flush: the test fails.)"""
    synced = _synced_paths(monkeypatch)
    atomic_write_bytes(tmp_path / "checkpoint.pt", b"weights", sync=True)
    assert len(synced) == 2 and Path(synced[0]).name.startswith(".checkpoint.pt.")
    assert synced[1] == str(tmp_path.resolve())


def test_a_file_system_that_cannot_flush_folders_is_said_once_and_carried_on(tmp_path, monkeypatch, capsys):
    """A folder's fsync answered with EINVAL (some network and virtual file systems): the synced write and the
    publish carry on, the file in place and no ``.X.old`` left, and one line says so. (Checked against a sync_folder
    that let the error through: the write raised after its rename.)"""
    import errno
    import stat

    real_fsync = os.fsync

    def folders_refuse(fd):
        if stat.S_ISDIR(os.fstat(fd).st_mode):
            raise OSError(errno.EINVAL, "Invalid argument")
        return real_fsync(fd)

    monkeypatch.setattr(files.os, "fsync", folders_refuse)
    monkeypatch.setattr(files, "_told_unsyncable", set())
    atomic_write_bytes(tmp_path / "checkpoint.pt", b"weights", sync=True)
    atomic_write_bytes(tmp_path / "checkpoint.pt", b"weights 2", sync=True)
    assert (tmp_path / "checkpoint.pt").read_bytes() == b"weights 2"
    out = _folder(tmp_path / "run", "old")
    publish_folder(_folder(tmp_path / ".run.partial", "new"), out)
    assert (out / "0.txt").read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == [
        "checkpoint.pt",
        "run",
    ]
    assert capsys.readouterr().err.count("cannot flush folders") == 1


def test_a_published_folder_is_flushed_before_the_old_one_goes(tmp_path, monkeypatch):
    """``publish_folder`` flushes every new file and the new folder before the rename, and the parent folder after
    it, all before the old folder is deleted. (Checked against a publish that flushed nothing: the test fails.)"""
    out = _folder(tmp_path / "run", "old")
    partial = _folder(tmp_path / ".run.partial", "new", n=2)
    synced = _synced_paths(monkeypatch)
    deleted = []
    real_rmtree = shutil.rmtree
    monkeypatch.setattr(files.shutil, "rmtree", lambda p, **k: (deleted.append(len(synced)), real_rmtree(p, **k)))
    publish_folder(partial, out)
    partial_path = str(partial.resolve())
    assert sorted(synced[:2]) == [f"{partial_path}/0.txt", f"{partial_path}/1.txt"] and synced[2] == partial_path
    assert synced[3] == str(tmp_path.resolve()) and deleted and min(deleted) >= 4


def test_the_lock_is_the_real_folders_whatever_the_path(tmp_path):
    """A path through a symbolic link takes the same lock as the folder's own path. (Checked against the lock keyed
    by the path as spelled: the second lock was granted.)"""
    (tmp_path / "disk" / "run").mkdir(parents=True)
    (tmp_path / "run").symlink_to(tmp_path / "disk" / "run")  # runs/<name> -> a folder elsewhere
    with folder_lock(tmp_path / "disk" / "run"):
        with pytest.raises(FolderBusy):
            with folder_lock(tmp_path / "run"):
                pass


def test_another_users_lock_file_is_locked_read_only(tmp_path, monkeypatch):
    """A lock file this user may not write (another user's, mode 0644: simulated, since the tests may run as root)
    is locked through a read-only open; the lock still excludes a second writer. (Checked against the read-write
    open only: PermissionError.)"""
    lock = tmp_path / ".run.lock"
    lock.write_text("")
    real_open = os.open

    def no_write(path, flags, *args):
        if Path(path) == lock and flags & os.O_RDWR:
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_open(path, flags, *args)

    monkeypatch.setattr(files.os, "open", no_write)
    with folder_lock(tmp_path / "run"):
        with pytest.raises(FolderBusy):
            with folder_lock(tmp_path / "run"):
                pass


def test_a_folder_where_no_lock_can_be_made_is_one_line(tmp_path, monkeypatch):
    """A read-only parent folder (simulated) ends in an OSError naming the lock file, which the commands print as
    one line. (Checked against the bare os.open: its message named the file but not why a lock was wanted.)"""
    real_open = os.open

    def read_only(path, flags, *args):
        if flags & os.O_CREAT:
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_open(path, flags, *args)

    monkeypatch.setattr(files.os, "open", read_only)
    with pytest.raises(OSError) as caught:
        with folder_lock(tmp_path / "run"):
            pass
    assert (
        _message(caught.value) == f"{tmp_path / '.run.lock'}: cannot create the lock file (the folder is not writable)"
    )


def test_two_writers_of_one_file_never_share_a_temporary_file(tmp_path):
    """``atomic_output`` gives each writer its own temporary name, so two writers of one video cannot write into
    one file and publish it truncated. (Checked against the fixed ``.<stem>.partial<suffix>`` name: the two
    names were equal.)"""
    path = tmp_path / "orbit.mp4"
    with atomic_output(path) as first, atomic_output(path) as second:
        assert first != second and first.suffix == second.suffix == ".mp4"
        first.write_bytes(b"first")
        second.write_bytes(b"second")
    assert path.read_bytes() in (b"first", b"second")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["orbit.mp4"]


def test_a_killed_writers_temporary_file_is_removed_by_the_next_writer(tmp_path):
    """A writer killed mid-write leaves ``.<stem>.partial-<pid>-<n><suffix>``; the next ``atomic_output`` of the same
    file removes it when that process is gone, and keeps a live writer's and other files' temporary files. (Checked
    against atomic_output without the removal: the dead writer's file stayed beside the finished video.)"""
    import subprocess
    import sys

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead, live = int(gone.stdout), os.getppid()
    path = tmp_path / "orbit.mp4"
    left = [tmp_path / f".orbit.partial-{dead}-0.mp4", tmp_path / f".orbit.partial-{live}-3.mp4"]
    other = tmp_path / f".orbit2.partial-{dead}-0.mp4"  # another file's: not this writer's to remove
    for stale in (*left, other):
        stale.write_bytes(b"half")
    with atomic_output(path) as tmp:
        tmp.write_bytes(b"whole")
    assert path.read_bytes() == b"whole"
    assert not left[0].exists() and left[1].exists() and other.exists()


@pytest.mark.parametrize(
    ("command", "main", "argv", "locked"),
    [
        ("narf-eval", "eval", ["--split", "novel_view", "--limit", "1"], "run"),
        ("narf-render-video", "render_video", ["--kind", "orbit", "--frames", "2", "--out", "OUT/orbit.mp4"], "out"),
        ("narf-export-mesh", "export_mesh", ["--frame", "0", "--out", "OUT/body.ply"], "out"),
    ],
)
def test_commands_that_write_beside_a_run_take_its_lock(command, main, argv, locked, tiny_run, tmp_path, capsys):
    """narf-eval takes the run's own lock (not only its eval folder's), so it never runs beside a fit of the run;
    narf-render-video and narf-export-mesh lock their output file. Each is refused in one line while another
    process (here: another open of the lock) holds it. (Checked against the commands without the lock: they ran.)"""
    import importlib

    from pipelines.cli.common import run_cli

    argv = [a.replace("OUT", str(tmp_path)) for a in argv]
    held = tiny_run if locked == "run" else Path(argv[argv.index("--out") + 1])
    with folder_lock(held):
        code = run_cli(command, importlib.import_module(f"pipelines.cli.{main}").main, ["--run", str(tiny_run), *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "another command is writing it" in err[0], err


def test_the_umask_is_read_not_set_where_linux_gives_it():
    """Importing fitting.files and writing a file never changes the process's umask where /proc gives it (setting
    it, even back, is process-wide: another thread creating a file in that instant gets the wrong mode). (Checked
    against the umask set and put back at import: os.umask was called.)"""
    import subprocess
    import sys

    if not Path("/proc/self/status").is_file():
        pytest.skip("no /proc/self/status: the umask can only be read by setting it")
    code = (
        "import os, sys, tempfile\ncalls = []\nreal = os.umask\nos.umask = lambda m: (calls.append(m), real(m))[1]\n"
        "from fitting.files import atomic_write_bytes, new_file_mode\n"
        "atomic_write_bytes(os.path.join(tempfile.mkdtemp(), 'f'), b'x')\nprint(calls, oct(new_file_mode()))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == "[]" and out[1] == oct(0o666 & ~_current_umask())


def _current_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def test_writers_into_a_capture_or_a_run_take_its_lock_first(tiny_run, tmp_path, capsys):
    """narf-camera-colour writes CAPTURE/colour.json and narf-eval --reference-params RUN/eval/joints.json: each
    takes the folder's lock before it reads or writes anything, so beside another writer of that folder both end at
    once with exit 2 and write nothing. (Checked against the commands without the lock: colour.json's command went
    on to read the capture, narf-eval wrote joints.json.)"""
    from pipelines.cli import camera_colour
    from pipelines.cli import eval as cli_eval_module
    from pipelines.cli.common import run_cli

    capture = tmp_path / "capture"
    capture.mkdir()
    with folder_lock(capture):
        assert run_cli("narf-camera-colour", camera_colour.main, [str(capture), "--quiet"]) == 2
    assert "another command is writing it" in capsys.readouterr().err and not (capture / "colour.json").exists()
    params, run = tmp_path / "params", tmp_path / "run"
    params.mkdir()
    shutil.copytree(tiny_run, run, ignore=shutil.ignore_patterns("eval"))  # the shared run's report is others'
    with folder_lock(run):
        args = ["--run", str(run), "--reference-params", str(params), "--quiet"]
        assert run_cli("narf-eval", cli_eval_module.main, args) == 2
    assert "another command is writing it" in capsys.readouterr().err
    assert not (run / "eval" / "joints.json").exists()


def test_a_sub_folder_moved_aside_by_a_killed_merge_comes_back(tmp_path):
    """A kill inside merge_folder after colmap/ was moved aside and before the new one came: restore_merged (which
    narf-calibrate runs first) puts it back; beside a complete new one it is deleted. (Checked against no restore:
    colmap/ stayed hidden as .colmap.old.)"""
    from fitting.files import restore_merged

    out = tmp_path / "calibration"
    _folder(out / ".colmap.old", "old")
    (out / "report.json").write_text("{}")
    restore_merged(out)
    assert _contents(out / "colmap") == {"old"} and not (out / ".colmap.old").exists()
    _folder(out / ".colmap.old", "older")
    restore_merged(out)
    assert _contents(out / "colmap") == {"old"} and not (out / ".colmap.old").exists()


def test_atomic_output_flushes_the_file_then_its_folder(tmp_path, monkeypatch):
    """Videos, plots and .mat files (atomic_output) reach the disk before their rename, and the rename is flushed.
    (Checked against the rename alone: nothing was flushed.)"""
    synced = _synced_paths(monkeypatch)
    with files.atomic_output(tmp_path / "video.mp4") as tmp:
        tmp.write_bytes(b"frames")
    assert len(synced) == 2 and Path(synced[0]).name.startswith(".video.partial-")
    assert synced[1] == str(tmp_path.resolve())


def test_a_large_tree_is_flushed_by_one_system_sync(tmp_path, monkeypatch):
    """A published folder of more than SYNC_TREE_FILES files (a capture's images) is flushed by one ``os.sync()``,
    not an fsync a file; a small one file by file, as before. (Checked against the file-by-file flush: 65 fsyncs.)"""
    synced, system = _synced_paths(monkeypatch), []
    monkeypatch.setattr(files.os, "sync", lambda: system.append(1))
    big = _folder(tmp_path / ".big.partial", "x", n=files.SYNC_TREE_FILES + 1)
    files.sync_tree(big)
    assert system == [1] and synced == []
    files.sync_tree(_folder(tmp_path / ".small.partial", "x", n=3))
    assert system == [1] and len(synced) == 4  # three files and their folder
