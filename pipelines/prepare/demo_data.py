"""The real demo recording: Pose2Sim's ``Demo_SinglePerson`` (BSD-3-Clause), taken from the ``pose2sim`` wheel on
PyPI without installing it (docs/guides/real-captures.md).

``python -m pipelines.prepare.demo_data CACHE OUT`` downloads the wheel into CACHE (once) and unpacks the demo
folders into OUT (``OUT/Demo_SinglePerson``, ``OUT/Demo_MultiPerson``). With ``--body25b`` it also unpacks Pose2Sim's
own OpenPose BODY_25B keypoints of the single-person demo (``OUT/Demo_SinglePerson_body25b``, one ``camNN_json``
folder per camera) from the 0.8.4 wheel, the last to ship them; that wheel's videos of the trial are the same
files, byte for byte.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import zipfile
from pathlib import Path

WHEEL = "pose2sim==0.10.49"
#: (wheel, folder inside it, folder written under OUT)
PARTS = (
    (WHEEL, "Pose2Sim/Demo_SinglePerson/", "Demo_SinglePerson"),
    (WHEEL, "Pose2Sim/Demo_MultiPerson/", "Demo_MultiPerson"),
)
BODY25B = (
    "pose2sim==0.8.4",
    "Pose2Sim/S00_Demo_BatchSession/S00_P00_SingleParticipant/S00_P00_T01_BalancingTrial/pose/",
    "Demo_SinglePerson_body25b",
)


def fetch_wheel(cache: Path, wheel: str = WHEEL) -> Path:
    """The wheel ``name==version`` in ``cache``, downloaded with pip when missing (no dependencies, nothing
    installed)."""
    name, version = wheel.split("==")
    path = cache / f"{name}-{version}-py3-none-any.whl"
    if not path.is_file():
        cache.mkdir(parents=True, exist_ok=True)
        command = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", wheel, "-d", str(cache)]
        subprocess.run(command, check=True)
    return path


def unpack(wheel: Path, prefix: str, target: Path, marker: str) -> Path:
    """Unpack the wheel's folder ``prefix`` into ``target``; a folder already complete (its ``.unpacked`` marker) is
    kept."""
    if (target / ".unpacked").is_file():
        return target
    with zipfile.ZipFile(wheel) as archive:
        for member in archive.namelist():
            if member.startswith(prefix) and not member.endswith("/") and ".." not in member:
                path = target / member[len(prefix) :]
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(archive.read(member))
    (target / ".unpacked").write_text(marker)
    return target


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m pipelines.prepare.demo_data", description=__doc__)
    parser.add_argument("cache", type=Path, help="where the wheels are downloaded (once)")
    parser.add_argument("out", type=Path, help="where the demo folders are unpacked")
    parser.add_argument("--body25b", action="store_true", help="also Pose2Sim's BODY_25B keypoints of the demo")
    args = parser.parse_args()
    for wheel, prefix, folder in PARTS + ((BODY25B,) if args.body25b else ()):
        print(f"demo recording: {unpack(fetch_wheel(args.cache, wheel), prefix, args.out / folder, wheel)}")


if __name__ == "__main__":
    main()
