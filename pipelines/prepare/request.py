"""What ``narf-prepare-capture`` is asked: one request that every stage of the prepare reads
(``pipelines.prepare.run``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from pipelines.datasets.floor import Floor
from pipelines.prepare.body.fit import FitSettings


@dataclass(frozen=True)
class PrepareRequest:
    """What ``narf-prepare-capture`` was asked (its ``--help`` says each)."""

    recording: Path
    out: Path
    calibration: Path | None = None
    start: int = 0
    stop: int | None = None
    stride: int = 1
    longest_side: int | None = None
    keypoints: Path | None = None
    keypoint_layout: str | None = None  # None: from the files' size (25 points checked)
    masks: Path | None = None
    camera_map: dict[str, str] | None = None
    holdout_camera: str | None = None
    novel_fraction: float = 0.3
    threshold: float = 0.03
    smpl_dir: Path | None = None
    fit: FitSettings = field(default_factory=FitSettings)
    floor: Floor | None = None  # None: found from the fitted feet
    overwrite: bool = False
    keep_flagged: bool = False  # write the capture even when every camera is flagged (for inspection)
    smpl_params: Path | None = None  # bodies the user brings (EasyMocap smpl/*.json or ZJU params/), not fitted
    person: int | None = None  # the person's id in smpl_params (None: the only one)
    follow: str | tuple = "best-seen"  # whom to follow among several people (prepare.people.tracks.parse_person)
    sync: str | dict[str, int] = "auto"  # auto, report, off, or whole-frame offsets by camera (prepare.sync.apply)
    progress: bool = True
