"""NARF's ``render_128`` renderer (``docs/formats.md §6.2-6.3``), shared by the THUman-like stand-in and by
``narf-prepare-thuman``, which renders real raw THUman items (NARF's own renderer needs Python 2 and opendr).

Per mesh: the SMPL-frame mesh and joint frames are flipped (diag(1, -1, -1)), centred on the hips and scaled by
0.5; per render, a random rotation R_x R_y R_z and scale U(1, 1.5) place the body and a camera is sampled on
NARF's orbit (novel views: any direction at 1.5-2.5 m). Each render has a ``_view2`` twin under another
training-distribution camera: the autoencoder's encoder input.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from fitting.files import fresh_partial, publish_folder, write_image, write_npy, writes_folder
from pipelines.body.model import BodyModel
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.thuman import RENDER_SIZE, THUMAN_K, item_gender, read_colored_obj, read_smpl_params_txt
from pipelines.synthetic.people import raycast

SPLITS = {"train": False, "same_view": False, "novel_view": True}  # split -> novel-view camera distribution
AXIS_FLIP = np.diag([1.0, -1.0, -1.0])  # NARF's axis_transformation
#: NARF renders with one fixed lighting for the autoencoder set; here two world lights and an ambient term.
LIGHTS = [(np.array([0.3, -0.8, -0.5]), 0.6), (np.array([-0.6, -0.2, -0.7]), 0.3)]


def _rotation(x: float, y: float, z: float) -> np.ndarray:
    rx, ry, rz = (cv2.Rodrigues(np.array(v, dtype=np.float64))[0] for v in ([x, 0, 0], [0, y, 0], [0, 0, z]))
    return rx @ ry @ rz


def sample_camera(rng: np.random.Generator, novel_view: bool) -> np.ndarray:
    """(4, 4) cam_from_world as NARF samples it: t = (0, 0, 2) (novel: t_z ~ U(1.5, 2.5)), rotation by
    U(0, 2 pi) about (sin th cos ph, cos th, sin th sin ph), th ~ U(0, 0.3) (novel: U(0, pi))."""
    t_z = rng.uniform(1.5, 2.5) if novel_view else 2.0
    theta = rng.uniform(0, np.pi) if novel_view else rng.uniform(0, 0.3)
    phi, angle = rng.uniform(0, 2 * np.pi), rng.uniform(0, 2 * np.pi)
    axis = np.array([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)])
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(axis * angle)[0]
    out[:3, 3] = [0.0, 0.0, t_z]
    return out


def narf_frame(vertices: np.ndarray, world_from_joint: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NARF's preprocessing of an SMPL-frame mesh: flip axes (bone_params), centre on the hips, scale by 0.5.

    Returns bone_params (24, 4, 4) after the flip, and the centred vertices (V, 3) and transforms (24, 4, 4).
    """
    bones = world_from_joint.copy()
    bones[:, :3] = AXIS_FLIP @ bones[:, :3]
    flipped = vertices @ AXIS_FLIP
    shift = -bones[[1, 2], :3, 3].mean(axis=0)
    centred = bones.copy()
    centred[:, :3, 3] = (bones[:, :3, 3] + shift) * 0.5
    return bones, (flipped + shift) * 0.5, centred


def _render_pair(mesh: tuple, bones, rng, novel_view: bool) -> list[tuple]:
    """One render and its _view2 copy: same random rotation/scale of the body, two cameras."""
    vertices, faces, colours = mesh
    rotation = _rotation(rng.uniform(-0.3, 0.3), rng.uniform(-np.pi, np.pi), rng.uniform(-0.3, 0.3))
    scale = rng.uniform(1.0, 1.5)
    world_vertices = vertices @ rotation.T * scale
    pose_to_world = bones.copy()
    pose_to_world[:, :3, :3] = rotation @ bones[:, :3, :3]
    pose_to_world[:, :3, 3] = bones[:, :3, 3] @ rotation.T * scale
    out = []
    for novel in (novel_view, False):
        cam_from_world = sample_camera(rng, novel)
        image = raycast(
            world_vertices,
            faces,
            colours,
            np.zeros(len(vertices), np.uint8),
            THUMAN_K,
            cam_from_world,
            RENDER_SIZE,
            RENDER_SIZE,
            LIGHTS,
        )
        out.append((image, cam_from_world @ pose_to_world, pose_to_world))
    return out


def _save_render(folder: Path, index: int, render: tuple) -> None:
    image, pose_to_camera, pose_to_world = render
    rgba = np.concatenate([image["rgb"], image["alpha"][..., None]], axis=-1)
    write_image(folder / f"color_{index:08d}.png", np.uint8(rgba * 255)[..., [2, 1, 0, 3]])
    write_npy(folder / f"pose_to_camera_{index:08d}.npy", pose_to_camera)
    write_npy(folder / f"pose_to_world_{index:08d}.npy", pose_to_world)


def prepare_folders(root: Path) -> None:
    for split in SPLITS:
        for name in (split, f"{split}_view2"):
            (root / name / "render_128" / "color").mkdir(parents=True, exist_ok=True)
        (root / split / "render_128" / "bone_params").mkdir(parents=True, exist_ok=True)


def render_mesh_splits(root: Path, m: int, mesh: tuple, world_from_joint: np.ndarray, per_mesh: dict, rng) -> None:
    """Render mesh ``m`` (vertices in the SMPL frame, faces, vertex colours) into every split and its twin, and
    save its bone_params."""
    bones, centred_vertices, centred_bones = narf_frame(mesh[0], world_from_joint)
    for split, novel in SPLITS.items():
        write_npy(root / split / "render_128" / "bone_params" / f"bone_params_{m:08d}.npy", bones)
        for view in range(per_mesh[split]):
            index = per_mesh[split] * m + view
            main, view2 = _render_pair((centred_vertices, mesh[1], mesh[2]), centred_bones, rng, novel)
            _save_render(root / split / "render_128" / "color", index, main)
            _save_render(root / f"{split}_view2" / "render_128" / "color", index, view2)


def raw_items(raw_dir: Path) -> list[str]:
    """Items of a raw THUman folder: its ``data_list.txt`` when present (NARF's order), else every
    ``<item>/<frame>/`` holding ``smpl_params.txt``, sorted."""
    raw_dir = Path(raw_dir)
    listing = raw_dir / "data_list.txt"
    if listing.is_file():
        items = [line.strip() for line in listing.read_text().splitlines() if line.strip()]
    else:
        items = sorted(str(p.parent.relative_to(raw_dir)) for p in raw_dir.glob("*/*/smpl_params.txt"))
    if not items:
        raise CaptureError(f"{raw_dir}: no raw THUman item (<item>/<frame>/smpl_params.txt) and no data_list.txt")
    return items


@writes_folder()
def prepare_thuman(
    raw_dir: Path,
    out: Path,
    renders_per_mesh: int = 10,
    train_fraction: float = 0.9,
    seed: int = 0,
    smpl_path=None,
    progress: bool = True,
) -> Path:
    """Render raw THUman items into NARF's autoencoder layout (``docs/formats.md §6``): the scan is moved into
    the SMPL frame (v <- (v - t) R), its joint frames come from ``smpl_params.txt`` through the body model, and
    the first ``train_fraction`` of the items train (the rest are novel poses, as NARF's list order)."""
    items = raw_items(raw_dir)
    meshes = []
    for item in items:  # read everything first: a malformed item fails before anything is written
        params = read_smpl_params_txt(Path(raw_dir) / item / "smpl_params.txt")
        scan = read_colored_obj(Path(raw_dir) / item / "mesh.obj")
        item_gender(Path(raw_dir) / item)
        meshes.append((params, scan))
    partial = fresh_partial(out)
    prepare_folders(partial)
    body = BodyModel(smpl_path, dtype=torch.float64)
    per_mesh = {"train": renders_per_mesh, "same_view": 1, "novel_view": 1}
    zeros = torch.zeros(1, 3, dtype=torch.float64)
    for m, (params, scan) in enumerate(tqdm(meshes, desc="rendering items", unit="mesh", disable=not progress)):
        rotation, translation = params.world_from_smpl[:3, :3], params.world_from_smpl[:3, 3]
        vertices = (scan.vertices - translation) @ rotation
        posed = body.pose_zju(torch.as_tensor(params.pose[None]), zeros, zeros, torch.as_tensor(params.betas[None]))
        mesh = (vertices, scan.faces, scan.colors)
        render_mesh_splits(
            partial, m, mesh, posed.world_from_joint[0].numpy(), per_mesh, np.random.default_rng([seed, m])
        )
    n_train = max(1, min(len(items) - 1, int(round(train_fraction * len(items))))) if len(items) > 1 else 1
    marker = {
        "dataset": "thuman",
        "source": str(raw_dir),
        "items": items,
        "n_meshes": len(items),
        "n_train_meshes": n_train,
        "renders_per_mesh": per_mesh,
    }
    (partial / "thuman.json").write_text(json.dumps(marker, indent=1))
    return publish_folder(partial, out)
