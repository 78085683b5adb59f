"""A synthetic capture written back as a raw recording, the way a studio hands one over (docs/guides/real-captures.md):
one mp4 per camera, a Qualisys ``.qca.txt`` of the true cameras, OpenPose-style JSON (BODY_25 unless asked)
projected from the true joints with pixel noise, and the true person masks. ``narf-prepare-capture`` on it must give
back the truth.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from fitting.files import write_image
from fitting.video import write_mp4
from pipelines.body.model import BodyModel
from pipelines.datasets.camera import project_distorted, silhouette
from pipelines.datasets.capture import ZjuCapture
from pipelines.datasets.keypoints import keypoints_from_joints, read_openpose, write_openpose
from pipelines.datasets.rig_files import write_qualisys


def true_joints(capture: ZjuCapture, body: BodyModel) -> np.ndarray:
    """(F, 24, 3) world joints of every frame, from the capture's SMPL parameters."""
    params = [capture.params(f) for f in range(capture.n_frames)]
    stack = [np.stack([getattr(p, k) for p in params]) for k in ("poses", "rh", "th", "shapes")]
    with torch.no_grad():
        return body.pose_zju(*stack).world_from_joint[..., :3, 3].numpy()


def forth_and_back(n: int, frames: int) -> list[int]:
    """The capture frame shown in each of ``frames`` recording frames: its ``n`` frames played forth, back, forth..."""
    return [f % n if (f // n) % 2 == 0 else n - 1 - f % n for f in range(frames)]


def write_recording(
    capture_root: Path,
    out: Path,
    noise_px: float = 1.0,
    seed: int = 0,
    fps: int = 30,
    layout: str = "body25",
    cameras: int | None = None,
    frames: int | None = None,
) -> Path:
    """Write ``out/videos/<camera>.mp4``, ``out/calibration/Calib.qca.txt``, ``out/keypoints/<camera>_json/`` and
    ``out/masks/<camera>/`` from a synthetic ZJU-layout capture (module docstring); the keypoints in ``layout``
    (``pipelines.datasets.keypoints.LAYOUT_SIZES``). ``cameras``: that many of the capture's cameras, evenly spread
    (None: all); ``frames``: that many frames, the capture's played forth and back (None: its own). Frames are
    streamed into the videos. Returns ``out``."""
    capture = ZjuCapture(capture_root, ratio=1.0, mask_source="mask")
    rng = np.random.default_rng(seed)
    joints = true_joints(capture, BodyModel())
    order = forth_and_back(capture.n_frames, frames or capture.n_frames)
    chosen = np.linspace(0, len(capture.cameras) - 1, cameras or len(capture.cameras)).round().astype(int)
    write_qualisys(out / "calibration" / "Calib.qca.txt", [capture.cameras[c] for c in chosen])

    def camera_frames(c: int, camera):
        for i, f in enumerate(order):
            mask = cv2.imread(str(capture.root / "mask" / Path(capture.ims[f][c]).with_suffix(".png")), 0)
            (out / "masks" / camera.name).mkdir(parents=True, exist_ok=True)
            write_image(out / "masks" / camera.name / f"{i:06d}.png", (mask > 0).astype(np.uint8) * 255)
            pixels = project_distorted(camera, joints[f]) + rng.normal(0.0, noise_px, (len(joints[f]), 2))
            path = out / "keypoints" / f"{camera.name}_json" / f"{camera.name}_{i:012d}_keypoints.json"
            write_openpose(path, [keypoints_from_joints(pixels, layout)])
            yield cv2.imread(str(capture.root / capture.ims[f][c]), cv2.IMREAD_COLOR)[..., ::-1]

    for c in chosen:
        camera = capture.cameras[c]
        write_mp4(out / "videos" / f"{camera.name}.mp4", camera_frames(c, camera), fps=fps)
    return out


#: where ``--people`` puts the others: from the first person's pelvis of frame 0 (metres, world)
PASSERS_BY = ((1.2, 0.0, 0.0), (-1.2, 0.0, 0.0))


def main(argv: list[str] | None = None) -> None:
    """``python -m pipelines.synthetic.recording CAPTURE OUT [--cameras N] [--frames N]``: a long recording to
    measure ``narf-prepare-capture`` on (docs/results/real-capture.md, *Long takes: memory and speed*)."""
    import argparse

    parser = argparse.ArgumentParser(description=write_recording.__doc__)
    parser.add_argument("capture", type=Path, help="a synthetic capture (narf-synth)")
    parser.add_argument("out", type=Path, help="the recording to write")
    parser.add_argument("--cameras", type=int, default=None, help="that many cameras, evenly spread (default: all)")
    parser.add_argument("--frames", type=int, default=None, help="that many frames, played forth and back")
    parser.add_argument(
        "--people", type=int, default=1, help="that many people: the others stand 1.2 m to either side (at most 3)"
    )
    args = parser.parse_args(argv)
    print(write_recording(args.capture, args.out, cameras=args.cameras, frames=args.frames))
    for i, side in enumerate(PASSERS_BY[: max(0, args.people - 1)]):
        add_passer_by(args.capture, args.out, np.array(side), np.zeros(3), frame_shift=5 + 7 * i, seed=1 + i)


def add_passer_by(
    capture_root: Path, recording: Path, offset: np.ndarray, step: np.ndarray, frame_shift: int = 5, seed: int = 1
) -> np.ndarray:
    """Put a second person into a recording written by :func:`write_recording` (BODY_25 keypoints): the stand-in body
    again, in the pose of frame ``f + frame_shift`` (modulo the frames), moved so that its pelvis stands at the first
    person's pelvis of frame 0 + ``offset + f * step`` (metres, world) in frame ``f``. The person is added to the
    keypoint files of the cameras that see six or more of its joints (first in the file, so that file order cannot
    decide whom the capture follows) and to those cameras' masks; the videos' pixels are left as they are. A
    recording longer than the capture is followed as :func:`write_recording` played it (:func:`forth_and_back`).
    Returns its (F, 24, 3) world joints."""
    capture = ZjuCapture(capture_root, ratio=1.0, mask_source="mask")
    body, rng = BodyModel(), np.random.default_rng(seed)
    n = capture.n_frames
    count = max(len(list((recording / "keypoints").glob(f"{c.name}_json/*.json"))) for c in capture.cameras)
    order = forth_and_back(n, count)  # the recording's frames, as write_recording played them
    params = [capture.params((order[f] + frame_shift) % n) for f in range(count)]
    stack = [np.stack([getattr(p, k) for p in params]) for k in ("poses", "rh", "th", "shapes")]
    with torch.no_grad():
        posed = body.pose_zju(*stack)
    pelvis = posed.world_from_joint[:, 0, :3, 3].numpy()
    first = true_joints(capture, body)[0, 0]
    moved = first + np.asarray(offset) + np.arange(count)[:, None] * np.asarray(step) - pelvis  # (F, 3)
    joints = posed.world_from_joint[..., :3, 3].numpy() + moved[:, None]
    vertices = posed.vertices.numpy() + moved[:, None]
    for camera in capture.cameras:
        files = sorted((recording / "keypoints" / f"{camera.name}_json").glob("*.json"))
        for f, path in enumerate(files):
            pixels = project_distorted(camera, joints[f]) + rng.normal(0.0, 1.0, (len(joints[f]), 2))
            inside = (pixels >= 0).all(-1) & (pixels < [camera.width, camera.height]).all(-1)
            if inside.sum() < 6:
                continue
            write_openpose(path, [keypoints_from_joints(pixels, "body25"), *read_openpose(path)])
            mask_path = recording / "masks" / camera.name / f"{f:06d}.png"
            mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE) > 0
            mask |= silhouette(camera, vertices[f], body.faces)
            write_image(mask_path, mask.astype(np.uint8) * 255)
    return joints


if __name__ == "__main__":
    main()
