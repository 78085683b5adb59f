"""Bodies a user already has: EasyMocap's per-frame SMPL JSON and ZJU-MoCap ``params/`` folders (docs/formats.md §9).

* EasyMocap (``<output>/smpl/000000.json``, one file per frame, what made ZJU-MoCap's fits): a JSON list of people,
  or ``{"annots": [...]}`` as newer versions write it; each ``{"id": int, "Rh": [[3]], "Th": [[3]], "poses": [[72]],
  "shapes": [[10]]}``, plus ``expression`` and hand poses for SMPL-H/X, which are not read. ``poses[:3]`` is usually
  zero, the global rotation being Rh.
* ZJU-MoCap ``params/{i}.npy`` (or ``new_params``): one person per file (``pipelines.datasets.zju_mocap.read_params``).

Both use ``X_world = R(Rh) X + Th``. A file's frame is the last digit group of its name (``000012.json`` -> 12).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipelines.datasets.errors import CaptureError
from pipelines.datasets.keypoints import frame_number
from pipelines.datasets.zju_mocap import SmplParams, read_params

SIZES = {"poses": 72, "Rh": 3, "Th": 3, "shapes": 10}


def body_files(folder: Path) -> dict[int, Path]:
    """The folder's per-frame body files (``*.json`` or ``*.npy``, not both), by frame number."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CaptureError(f"{folder}: no such folder of SMPL parameters (EasyMocap smpl/*.json or ZJU params/*.npy)")
    kinds = {suffix: sorted(folder.glob(f"*{suffix}")) for suffix in (".json", ".npy")}
    if kinds[".json"] and kinds[".npy"]:
        raise CaptureError(f"{folder}: holds both .json and .npy files; give a folder of one kind")
    files = kinds[".json"] or kinds[".npy"]
    if not files:
        raise CaptureError(f"{folder}: no EasyMocap *.json or ZJU-MoCap *.npy SMPL parameter files")
    out = {}
    for path in files:
        frame = frame_number(path)
        if frame in out:
            raise CaptureError(f"{path}: frame {frame} also in {out[frame].name}")
        out[frame] = path
    return out


def read_easymocap_people(path: Path) -> list[tuple[int | None, SmplParams]]:
    """(id, parameters) of every person of one EasyMocap SMPL file, checked: numbers, finite, SMPL's sizes."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CaptureError(f"{path}: not an EasyMocap SMPL file ({type(err).__name__}: {err})") from None
    people = data.get("annots") if isinstance(data, dict) else data
    if not isinstance(people, list):
        raise CaptureError(f'{path}: expected a list of people, or {{"annots": [...]}}')
    out = []
    for p, person in enumerate(people):
        if not isinstance(person, dict):
            raise CaptureError(f"{path}: person {p} is not an object with Rh, Th, poses and shapes")
        values = {}
        for key, size in SIZES.items():
            try:
                array = np.asarray(person[key], dtype=np.float64).reshape(-1)
            except KeyError:
                raise CaptureError(f"{path}: person {p} has no '{key}'") from None
            except (TypeError, ValueError):
                raise CaptureError(f"{path}: person {p}'s '{key}' holds something other than numbers") from None
            if key == "shapes" and array.size != size:
                raise CaptureError(
                    f"{path}: person {p} has {array.size} shape values; SMPL's are {size} (another body model's?)"
                )
            if array.size < size or not np.isfinite(array).all():
                raise CaptureError(f"{path}: person {p}'s '{key}' needs {size} finite numbers, has {array.size}")
            values[key] = array[:size].astype(np.float32)
        ident = person.get("id")
        out.append(
            (
                ident if isinstance(ident, int) and not isinstance(ident, bool) else None,
                SmplParams(values["poses"], values["Rh"], values["Th"], values["shapes"]),
            )
        )
    return out


def read_body(path: Path, person: int | None) -> SmplParams | None:
    """One frame's body: person ``person`` (by id; None: the only one) of the file, or None when it is not there."""
    if Path(path).suffix == ".npy":
        return read_params(Path(path))
    people = read_easymocap_people(path)
    if person is None:
        if len(people) > 1:
            ids = [i for i, _ in people]
            raise CaptureError(f"{path}: {len(people)} people (ids {ids}); choose one with --person ID")
        return people[0][1] if people else None
    return next((params for ident, params in people if ident == person), None)


def bodies_for_frames(folder: Path, frames: list[int], person: int | None) -> list[SmplParams]:
    """The bodies of source frames ``frames`` from ``folder`` (:func:`body_files`), every one required."""
    files = body_files(folder)
    missing = [f for f in frames if f not in files]
    if missing:
        span = f"{min(files)}..{max(files)}"
        raise CaptureError(
            f"{folder}: no body for {len(missing)} of the {len(frames)} frames kept (first: frame {missing[0]}); its "
            f"{len(files)} files cover frames {span}"
        )
    out = []
    for frame in frames:
        body = read_body(files[frame], person)
        if body is None:
            raise CaptureError(f"{files[frame]}: no person with id {person}")
        out.append(body)
    return out
