"""A THUman-like set in NARF's layout (``docs/formats.md §6``), from the stand-in body: many people, each in a
few poses; ``render_128`` splits rendered as NARF's ``render_THUman.py`` renders them (``narf_render``), with
the ``_view2`` encoder-input copies; and raw items (``mesh.obj`` with vertex colours, ``smpl.obj``, CRLF
``smpl_params.txt``, ``cam.txt``) for ``narf-prepare-thuman``.

Meshes are ordered person-major within two blocks: every person's training poses first, then every person's
held-out poses (novel pose = mesh index >= ``n_train_meshes``, as NARF's autoencoder split takes the last meshes
of its list). ``synthetic.json`` is written last, into a staging folder that is renamed when complete.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from fitting.files import writes_folder
from pipelines.body.model import BodyModel
from pipelines.synthetic.narf_render import prepare_folders, render_mesh_splits
from pipelines.synthetic.people import Person, person_colours, random_person, random_poses
from pipelines.synthetic.settings import ThumanSynthConfig  # noqa: F401 (re-exported)
from pipelines.synthetic.staging import is_finished, publish, start_staging

THUMAN_VERSION = 2  # 2: a share of the people in swimwear (people.SWIMWEAR_SHARE)


def _mesh_plan(config: ThumanSynthConfig) -> list[tuple[int, int]]:
    """(person, pose slot) per mesh: every person's training poses, then every person's held-out poses."""
    train = [(p, k) for p in range(config.people) for k in range(config.train_poses)]
    held = [(p, config.train_poses + k) for p in range(config.people) for k in range(config.novel_poses)]
    return train + held


def _obj_text(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None) -> str:
    rows = np.hstack([vertices, colours]) if colours is not None else vertices
    lines = ["v " + " ".join(f"{v:.6f}" for v in row) for row in rows]
    lines += [f"f {a} {b} {c}" for a, b, c in faces + 1]
    return "\n".join(lines) + "\n"


def write_raw_item(folder: Path, betas, pose, vertices_smpl, faces, colours, rng: np.random.Generator) -> None:
    """A raw THUman item: the scan is the SMPL mesh placed as ``M R^T + t`` (a rotation about the origin)."""
    folder.mkdir(parents=True, exist_ok=True)
    root = np.eye(4)
    root[:3, :3] = cv2.Rodrigues(np.array([0.0, rng.uniform(-np.pi, np.pi), 0.0]))[0]
    root[:3, 3] = rng.uniform(-0.3, 0.3, 3)
    scan = vertices_smpl @ root[:3, :3].T + root[:3, 3]
    (folder / "mesh.obj").write_text(_obj_text(scan, faces, colours))
    (folder / "smpl.obj").write_text(_obj_text(scan, faces, None))
    lines = ["ShapeParams", " ".join(f"{b:.6f}" for b in betas) + " ", "RootTransformation"]
    lines += [" ".join(f"{v:.6f}" for v in row) + " " for row in root]
    lines += ["JointRotations"] + [f"{v:.6f}" for v in pose]
    (folder / "smpl_params.txt").write_bytes(("\r\n".join(lines) + "\r\n").encode())
    cam = np.eye(4)
    cam[:3, 3] = [0.0, 0.0, 2.5] - root[:3, 3]  # a depth camera 2.5 m in front of the scan
    (folder / "cam.txt").write_text("\n".join(" ".join(f"{v:.6f}" for v in row) for row in cam) + "\n")


def is_thuman_complete(out: Path, config: ThumanSynthConfig | None = None) -> bool:
    """True when ``out`` holds a finished THUman-like set (with these settings, if ``config`` is given)."""
    return is_finished(out, "thuman", config, THUMAN_VERSION)


def _write_mesh(root: Path, state: dict, m: int, person: Person, pose: np.ndarray, rng, config) -> None:
    betas = torch.as_tensor(person.betas, dtype=torch.float32)[None]
    body = state["body"].pose_zju(
        torch.as_tensor(pose, dtype=torch.float32)[None], torch.zeros(1, 3), torch.zeros(1, 3), betas
    )
    vertices = body.vertices[0].double().numpy()
    mesh = (vertices, state["faces"], state["colours"])
    per_mesh = {"train": config.renders_per_mesh, "same_view": 1, "novel_view": 1}
    render_mesh_splits(root, m, mesh, body.world_from_joint[0].double().numpy(), per_mesh, rng)
    if m < config.raw_items:
        item = f"results_syn_20260101_person{state['person_index']:03d}_1_{person.gender[0].upper()}"
        folder = root / "raw" / item / f"{state['pose_slot']:04d}"
        write_raw_item(folder, person.betas, pose, vertices, state["faces"], state["colours"], rng)
        state["data_list"].append(f"{item}/{state['pose_slot']:04d}")


@writes_folder()
def generate_thuman(
    out: str | Path, config: ThumanSynthConfig = ThumanSynthConfig(), smpl_path=None, progress: bool = True
) -> Path:
    """Generate (or reuse) the THUman-like set at ``out`` (module docstring); returns ``out``."""
    config.validate()
    out = Path(out)
    if is_thuman_complete(out, config):
        return out
    partial = start_staging(out, "thuman", "THUman-like set")
    prepare_folders(partial)
    body = BodyModel(smpl_path)
    rng = np.random.default_rng(config.seed)
    people = [random_person(rng) for _ in range(config.people)]
    poses = [random_poses(config.train_poses + config.novel_poses, rng) for _ in people]
    weights = body.smpl.lbs_weights.numpy()
    state = {"body": body, "faces": body.faces.astype(np.int64), "labels": np.zeros(body.n_vertices, np.uint8)}
    state["data_list"] = []
    plan = _mesh_plan(config)
    for m, (p, slot) in enumerate(tqdm(plan, desc="thuman meshes", unit="mesh", disable=not progress)):
        rest = body.rest_body(torch.as_tensor(people[p].betas, dtype=torch.float32)[None]).vertices[0].numpy()
        state.update(colours=person_colours(people[p], rest, weights), person_index=p, pose_slot=slot)
        _write_mesh(partial, state, m, people[p], poses[p][slot], np.random.default_rng([config.seed, m]), config)
    (partial / "raw").mkdir(exist_ok=True)
    (partial / "raw" / "data_list.txt").write_text("\n".join(state["data_list"]) + "\n")
    marker = {
        "dataset": "thuman",
        "version": THUMAN_VERSION,
        "config": asdict(config),
        "n_meshes": len(plan),
        "n_train_meshes": config.people * config.train_poses,
        "renders_per_mesh": {"train": config.renders_per_mesh, "same_view": 1, "novel_view": 1},
        "mesh_person": [p for p, _ in plan],
    }
    return publish(partial, out, marker)
