"""The settings of the synthetic generators (``narf-synth``): plain dataclasses in a module that imports nothing
heavy, so that ``narf-synth --help`` reads their defaults without loading torch, trimesh or OpenCV. The generators
(``capture``, ``degrade``, ``rigid``, ``surreal``, ``thuman``) import them from here."""

from __future__ import annotations

from dataclasses import dataclass

#: Subjects the synthetic generator can stand in for.
SYNTHETIC_SUBJECTS = ("taichi",)


@dataclass(frozen=True)
class SynthConfig:
    """Settings of a synthetic capture.

    Attributes:
        subject: name written into the marker (the motion is the taichi sequence).
        resolution: square image size in pixels.
        frames: number of frames (30 fps).
        cameras: number of ring cameras.
        seed: seed of rig, motion and appearance jitter.
        layout: ``standard`` (``Camera_B1/000000.jpg``) or ``313`` (``Camera (1)/..._0001_<time>.jpg``, 1-based).
        calib_shots: ChArUco board poses under ``calib/`` seen by the whole rig (0 to skip calib/).
        calib_close_ups: per-camera close-up board shots under ``calib/<camera>/intrinsics/``.
        jpeg_quality: JPEG quality of the images.
        workers: render processes.
        lbs: also write animatable_nerf's ``lbs/`` folder (per-frame weight grids: several MB a frame).
    """

    subject: str = "taichi"
    resolution: int = 512
    frames: int = 300
    cameras: int = 21
    seed: int = 0
    layout: str = "standard"
    calib_shots: int = 30
    calib_close_ups: int = 20
    jpeg_quality: int = 95
    workers: int = 2
    lbs: bool = False

    def validate(self) -> None:
        if self.resolution < 32 or self.frames < 1 or self.cameras < 1:
            raise ValueError(f"resolution >= 32, frames >= 1 and cameras >= 1 are required, got {self}")
        if self.layout not in ("standard", "313"):
            raise ValueError(f"layout must be 'standard' or '313', got '{self.layout}'")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be in [1, 100], got {self.jpeg_quality}")
        if self.calib_shots < 0 or self.calib_close_ups < 0:
            raise ValueError(f"calib_shots and calib_close_ups must be >= 0, got {self}")


@dataclass(frozen=True)
class Degradation:
    """How to break a capture.

    Attributes:
        pose_degrees: every joint of every frame (and the whole body, about its pelvis) turned by this angle about
            a random axis, independently per frame and joint.
        shift_m: every frame's body moved by this distance (metres) in a random direction.
        colour_spread: camera c's channel gains are ``exp(u)`` with u uniform in [-s, s] and its biases uniform in
            [-s/4, s/4], both with mean zero over the cameras; 0 leaves the images as they are.
        seed: seed of the draws.
    """

    pose_degrees: float = 4.0
    shift_m: float = 0.02
    colour_spread: float = 0.0
    seed: int = 0

    def validate(self) -> None:
        if not (0 <= self.pose_degrees < 180 and 0 <= self.shift_m < 1 and 0 <= self.colour_spread < 1):
            raise ValueError(f"pose degrees in [0, 180), shift in [0, 1) m and colour spread in [0, 1), got {self}")


@dataclass(frozen=True)
class RigidSynthConfig:
    """Size of the rigid-object set: ``train`` / ``test`` images of ``resolution``^2 (supplement: 480 / 20 at 200)."""

    train: int = 480
    test: int = 20
    resolution: int = 200
    seed: int = 0

    def validate(self) -> None:
        if self.train < 1 or self.test < 1 or self.resolution < 16:
            raise ValueError(f"train >= 1, test >= 1 and resolution >= 16 are required, got {self}")


@dataclass(frozen=True)
class SurrealSynthConfig:
    """Size of the SURREAL-like set: ``clips`` clips of ``frames`` frames (30 fps), one person each, in
    ``<split>/run0/<seq>/``; betas ~ N(0, beta_std^2) (wider than the THUman-like set)."""

    clips: int = 12
    frames: int = 40
    split: str = "test"
    beta_std: float = 1.5
    seed: int = 0

    def validate(self) -> None:
        if self.clips < 1 or self.frames < 2:
            raise ValueError(f"clips >= 1 and frames >= 2 are required, got {self}")


@dataclass(frozen=True)
class ThumanSynthConfig:
    """Size of the THUman-like set.

    Attributes:
        people: number of people. train_poses / novel_poses: meshes per person for training / held out.
        renders_per_mesh: train renders per mesh (NARF's ``all``: 10; same_view and novel_view: 1 each).
        raw_items: how many meshes also get a raw item folder. seed: everything is deterministic under it.
    """

    people: int = 40
    train_poses: int = 4
    novel_poses: int = 1
    renders_per_mesh: int = 10
    raw_items: int = 8
    seed: int = 0

    def validate(self) -> None:
        if min(self.people, self.train_poses, self.renders_per_mesh) < 1 or min(self.novel_poses, self.raw_items) < 0:
            raise ValueError(f"people, train_poses and renders_per_mesh must be >= 1, got {self}")
