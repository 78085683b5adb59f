"""Synthetic multi-view capture of the stand-in body in the real ZJU-MoCap layout (docs/formats.md §4.2).

``generate_capture(out, SynthConfig(...))`` renders with trimesh + embree (ray casting through the distorted
pixel grid of every camera), writes images, CIHP and binary masks, ``params`` / ``vertices`` (no pose blend
shapes), ``new_params`` / ``new_vertices`` (with), ``annots.npy``, EasyMocap cameras and ChArUco calibration
shots under ``calib/``. The capture is written into a hidden ``.partial`` folder and renamed when complete, so
an interrupted run leaves nothing that looks finished; a finished capture with the same settings is reused.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import shutil
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import torch
import trimesh
from tqdm import tqdm

from fitting.files import fresh_partial, publish_folder, write_image, write_npy, writes_folder
from fitting.mesh import vertex_normals
from pipelines.body.locate import BODY_MODEL_RECORD, body_model_record
from pipelines.body.model import BodyModel
from pipelines.datasets.camera import Camera
from pipelines.datasets.capture import make_protocol
from pipelines.datasets.easymocap import write_easymocap_cameras
from pipelines.datasets.zju_mocap import SmplParams, write_annots, write_params
from pipelines.synthetic.scene import (
    albedo,
    facing_normals,
    pixel_directions,
    ring_cameras,
    shade,
    studio_background,
    taichi_motion,
    vertex_regions,
)
from pipelines.synthetic.settings import SYNTHETIC_SUBJECTS, SynthConfig  # noqa: F401 (re-exported)

GENERATOR_VERSION = 4  # 2: tilted, closer ChArUco board poses; 3: supersampled shots, per-camera close-ups;
# 4: true surfaces of the held-out evaluation frames (surfaces/)
MARKER = "synthetic.json"


def image_relpath(layout: str, cam: int, frame: int) -> str:
    """Relative image path of (camera index, frame index) in the given naming layout."""
    if layout == "313":
        return f"Camera ({cam + 1})/CoreView_313_Camera_({cam + 1})_{frame + 1:04d}_2019-08-23_16-08-50.592.jpg"
    return f"Camera_B{cam + 1}/{frame:06d}.jpg"


_STATE: dict = {}


def _prepare_state(state: dict) -> None:
    """Fill the module state used by the render functions (inherited by forked workers)."""
    _STATE.clear()
    _STATE.update(state)
    _STATE["dirs"] = [pixel_directions(cam) for cam in state["cameras"]]
    _STATE["backgrounds"] = [studio_background(cam, d) for cam, d in zip(state["cameras"], _STATE["dirs"])]


def _init_worker() -> None:
    cv2.setNumThreads(1)
    torch.set_num_threads(1)


def _bbox_pixels(camera: Camera, vertices: np.ndarray, pad: int = 6) -> tuple[int, int, int, int] | None:
    corners = np.array(np.meshgrid(*zip(vertices.min(0), vertices.max(0)))).T.reshape(-1, 3)
    rvec = cv2.Rodrigues(camera.cam_from_world[:3, :3])[0]
    if np.any((corners @ camera.cam_from_world[:3, :3].T + camera.cam_from_world[:3, 3])[:, 2] <= 0.05):
        return 0, 0, camera.width, camera.height
    pts = cv2.projectPoints(corners, rvec, camera.cam_from_world[:3, 3], camera.K, camera.dist)[0][:, 0]
    x0, y0 = np.floor(pts.min(0)).astype(int) - pad
    x1, y1 = np.ceil(pts.max(0)).astype(int) + pad
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, camera.width), min(y1, camera.height)
    return None if x1 <= x0 or y1 <= y0 else (x0, y0, x1, y1)


def render_view(mesh: trimesh.Trimesh, normals: np.ndarray, cam: int) -> tuple[np.ndarray, np.ndarray]:
    """Render one camera of the current frame, ``normals`` its (V, 3) vertex normals: (H, W, 3) float RGB and
    (H, W) uint8 CIHP labels."""
    camera = _STATE["cameras"][cam]
    image = _STATE["backgrounds"][cam].copy()
    labels = np.zeros((camera.height, camera.width), np.uint8)
    box = _bbox_pixels(camera, mesh.vertices)
    if box is None:
        return image, labels
    x0, y0, x1, y1 = box
    dirs = _STATE["dirs"][cam][y0:y1, x0:x1].reshape(-1, 3).astype(np.float64)
    origins = np.broadcast_to(camera.centre, dirs.shape)
    tri, ray, loc = mesh.ray.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
    if len(ray) == 0:
        return image, labels
    faces = mesh.faces[tri]
    bary = trimesh.triangles.points_to_barycentric(mesh.vertices[faces], loc)
    rest = np.einsum("nk,nkd->nd", bary, _STATE["rest_vertices"][faces])
    label = _STATE["labels"][faces[np.arange(len(faces)), bary.argmax(1)]]
    colour = shade(albedo(rest, label), facing_normals(bary, normals[faces], dirs[ray]))
    rows, cols = ray // (x1 - x0) + y0, ray % (x1 - x0) + x0
    image[rows, cols] = colour
    labels[rows, cols] = label
    return image, labels


def _render_frame(task: tuple[int, np.ndarray]) -> int:
    frame, vertices = task
    mesh = trimesh.Trimesh(vertices.astype(np.float64), _STATE["faces"], process=False)
    root, layout, quality = _STATE["root"], _STATE["layout"], _STATE["jpeg_quality"]
    normals = vertex_normals(mesh.vertices, mesh.faces)
    for cam in range(len(_STATE["cameras"])):
        image, labels = render_view(mesh, normals, cam)
        rel = Path(image_relpath(layout, cam, frame))
        bgr = cv2.cvtColor((image * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR)
        write_image(root / rel, bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
        write_image(root / "mask_cihp" / rel.with_suffix(".png"), labels)
        write_image(root / "mask" / rel.with_suffix(".png"), (labels > 0).astype(np.uint8))
    return frame


def pose_sequence(body: BodyModel, motion: dict[str, np.ndarray]) -> tuple[list[SmplParams], np.ndarray, np.ndarray]:
    """Pose the motion, put the feet on the floor (z = 0), return params and vertices without / with pose
    blend shapes, (F, V, 3) each."""
    args = [torch.as_tensor(motion[k], dtype=torch.float32) for k in ("poses", "Rh", "Th", "shapes")]
    old, new = [], []
    for start in range(0, len(args[0]), 64):
        chunk = [a[start : start + 64] for a in args]
        with torch.no_grad():
            old.append(body.pose_zju(*chunk, pose_blendshapes=False).vertices.numpy())
            new.append(body.pose_zju(*chunk, pose_blendshapes=True).vertices.numpy())
    old, new = np.concatenate(old), np.concatenate(new)
    lift = new[..., 2].max(axis=1)  # z is down: the lowest point has the largest z
    old[..., 2] -= lift[:, None]
    new[..., 2] -= lift[:, None]
    th = motion["Th"].copy()
    th[:, 2] -= lift
    params = [
        SmplParams(
            motion["poses"][f].astype(np.float32),
            motion["Rh"][f].astype(np.float32),
            th[f].astype(np.float32),
            motion["shapes"][f].astype(np.float32),
        )
        for f in range(len(th))
    ]
    return params, old, new


def _render_frames(state: dict, vertices: np.ndarray, config: SynthConfig, progress: bool) -> None:
    """Render and write every frame of every camera, in ``config.workers`` forked processes."""
    tasks = [(f, vertices[f]) for f in range(config.frames)]
    bar = tqdm(
        total=config.frames,
        desc=f"rendering {config.frames} frames x {config.cameras} cameras",
        unit="frame",
        disable=not progress,
    )
    _prepare_state(state)
    if config.workers > 1:
        with mp.get_context("fork").Pool(config.workers, _init_worker) as pool:
            for _ in pool.imap_unordered(_render_frame, tasks, chunksize=2):
                bar.update()
    else:
        for task in tasks:
            _render_frame(task)
            bar.update()
    bar.close()


def is_complete(out: Path, config: SynthConfig | None = None) -> bool:
    """True when ``out`` holds a finished capture (with the same settings, if ``config`` is given)."""
    marker = Path(out) / MARKER
    if not marker.is_file():
        return False
    if config is None:
        return True
    try:
        written = json.loads(marker.read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return written.get("config") == asdict(config) and written.get("version") == GENERATOR_VERSION


def _write_sequence(root: Path, layout: str, params: list[SmplParams], old: np.ndarray, new: np.ndarray) -> None:
    for folder in ("params", "new_params", "vertices", "new_vertices"):
        (root / folder).mkdir(parents=True, exist_ok=True)
    base = 1 if layout == "313" else 0
    for f, p in enumerate(params):
        write_params(root / "params" / f"{f + base}.npy", p)
        write_params(root / "new_params" / f"{f + base}.npy", p)
        write_npy(root / "vertices" / f"{f + base}.npy", old[f].astype(np.float32))
        write_npy(root / "new_vertices" / f"{f + base}.npy", new[f].astype(np.float32))


def surface_frames(n_frames: int, n_cameras: int) -> list[int]:
    """The held-out frames whose true surface the generator writes: the novel-pose evaluation frames of both
    protocols (docs/formats.md §4.2)."""
    frames = set()
    for name in ("narf", "neuralbody"):
        frames |= {f for f, _ in make_protocol(name, n_frames, n_cameras).split("novel_pose")}
    return sorted(frames)


def write_true_surfaces(root: Path, faces: np.ndarray, vertices: np.ndarray, n_cameras: int) -> None:
    """``surfaces/<frame>.ply``: the rendered body of each held-out evaluation frame, world metres."""
    (root / "surfaces").mkdir(exist_ok=True)
    for frame in surface_frames(len(vertices), n_cameras):
        mesh = trimesh.Trimesh(vertices[frame].astype(np.float64), faces, process=False)
        mesh.export(root / "surfaces" / f"{frame}.ply")


def _write_cameras(root: Path, config: SynthConfig, cameras: list[Camera]) -> None:
    """The image folders of every camera, ``annots.npy`` (cameras and image paths) and EasyMocap's yml files."""
    ims = [[image_relpath(config.layout, c, f) for c in range(config.cameras)] for f in range(config.frames)]
    for folder in ("", "mask_cihp", "mask"):
        for cam in cameras:
            (root / folder / cam.name).mkdir(parents=True, exist_ok=True)
    write_annots(root / "annots.npy", cameras, ims)
    write_easymocap_cameras(root, cameras)


@writes_folder()
def generate_capture(
    out: str | Path, config: SynthConfig = SynthConfig(), smpl_path: str | Path | None = None, progress: bool = True
) -> Path:
    """Generate (or reuse) a synthetic capture at ``out``; returns ``out``."""
    config.validate()
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out}: exists and is not a folder")
    if is_complete(out, config):
        return out
    if out.exists() and any(out.iterdir()):
        if not is_complete(out):
            raise FileExistsError(
                f"{out}: folder is not empty and holds no finished synthetic capture; choose another --out or remove it"
            )  # a finished capture with other settings: regenerated, and replaced once the new one is complete
    partial = fresh_partial(out)
    try:
        _write_capture(partial, config, smpl_path, progress)
    except BaseException:  # a full disk or Ctrl-C: no half-written capture left beside the old one
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return publish_folder(partial, out)


def _write_capture(partial: Path, config: SynthConfig, smpl_path, progress: bool) -> None:
    """Every file of the capture into the staging folder ``partial``."""
    body = BodyModel(smpl_path)
    params, old, new = pose_sequence(body, taichi_motion(config.frames, config.seed))
    cameras = ring_cameras(config.cameras, config.resolution, config.seed)
    if config.layout == "313":
        cameras = [
            Camera(f"Camera ({c + 1})", cam.K, cam.dist, cam.cam_from_world, cam.width, cam.height)
            for c, cam in enumerate(cameras)
        ]
    _write_sequence(partial, config.layout, params, old, new)
    _write_cameras(partial, config, cameras)
    rest = body.rest_body(torch.as_tensor(params[0].shapes)[None]).vertices[0].numpy()
    state = {
        "root": partial,
        "layout": config.layout,
        "jpeg_quality": config.jpeg_quality,
        "cameras": cameras,
        "faces": body.faces,
        "rest_vertices": rest,
        "labels": vertex_regions(rest, body.skinning_weights.numpy()),
    }
    _render_frames(state, new, config, progress)
    write_true_surfaces(partial, body.faces, new, config.cameras)
    if config.lbs:
        from pipelines.synthetic.lbs import write_lbs

        base = 1 if config.layout == "313" else 0
        write_lbs(partial, body, params, new, [f + base for f in range(config.frames)])
    if config.calib_shots > 0:
        from pipelines.synthetic.charuco_shots import write_calibration_shots

        write_calibration_shots(
            partial / "calib",
            cameras,
            config.calib_shots,
            config.seed,
            progress=progress,
            close_ups=config.calib_close_ups,
        )
    (partial / BODY_MODEL_RECORD).write_text(json.dumps(body_model_record(body.path), indent=1))
    (partial / MARKER).write_text(
        json.dumps({"version": GENERATOR_VERSION, "config": asdict(config), "smpl": str(body.path)}, indent=2)
    )
