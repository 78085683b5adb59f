"""Glue between a THUman-layout set on disk (NARF's ``render_128`` splits, ``docs/formats.md §6``) and the
autoencoder: find the set (a real one, else the synthetic stand-in, generated on demand), read renders with their
``_view2`` encoder inputs and poses, fit the part boxes, and start (or resume) an AutoencoderTrainer (the CNN
baseline: a CnnAutoencoderTrainer)."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from fitting.autoencoder import AutoencoderData
from fitting.config import FitConfig
from fitting.data import TrainingSet
from fitting.trainers import trainer_class
from pipelines.body.model import BodyModel, pose_batch_from_joints
from pipelines.datasets.camera import Camera
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.smpl_files import cache_dir
from pipelines.datasets.subjects import data_root
from pipelines.datasets.thuman import ThumanView, count_renders, read_render
from pipelines.synthetic.staging import use_stand_in
from pipelines.synthetic.thuman import ThumanSynthConfig, generate_thuman, is_thuman_complete

#: The supplement's autoencoder split: the first 3545 of THUman's 3939 meshes train, the rest are novel poses.
NARF_TRAIN_MESHES = 3545
SPLITS = ("train", "same_view", "novel_view")


@dataclass(frozen=True)
class ThumanSet:
    """A THUman-layout set: its root, mesh counts and renders per mesh of each split."""

    root: Path
    n_meshes: int
    n_train_meshes: int
    renders_per_mesh: dict

    def color_dir(self, split: str, view2: bool = False) -> Path:
        return self.root / (f"{split}_view2" if view2 else split) / "render_128" / "color"


def view_of_render(render, name: str) -> ThumanView:
    """A render_128 view with its camera: cam_from_world = pose_to_camera pose_to_world^-1 (any joint; the root)."""
    cam_from_world = render.pose_to_camera[0] @ np.linalg.inv(render.pose_to_world[0])
    camera = Camera(name, render.K, np.zeros(5), cam_from_world, 128, 128)
    return ThumanView(render.image, render.mask, np.zeros(render.mask.shape, bool), camera)


def resolve_thuman(config: FitConfig, quiet: bool = False, generate: bool = True) -> Path:
    """The set of ``data.data_root``: the folder itself when it holds ``train/render_128``, else
    ``<root>/synthetic/thuman`` (the stand-in, generated when missing and announced on stderr)."""
    explicit = Path(config.data.data_root) if config.data.data_root else None
    if explicit is not None and (explicit / "train" / "render_128").is_dir():
        return explicit
    out = data_root(config.data.data_root) / "synthetic" / "thuman"
    make = lambda: generate_thuman(out, ThumanSynthConfig())  # noqa: E731
    return use_stand_in(out, "THUman render_128 set", "thuman", is_thuman_complete, make, quiet, generate)


def open_thuman(root: Path, config: FitConfig) -> ThumanSet:
    """Mesh counts from the set's ``synthetic.json`` (the stand-in) or ``thuman.json`` (``narf-prepare-thuman``)
    when present, else from the train renders and the config (NARF's own renders)."""
    marker = next((root / name for name in ("synthetic.json", "thuman.json") if (root / name).is_file()), None)
    if marker is not None:
        written = json.loads(marker.read_text())
        return ThumanSet(root, written["n_meshes"], written["n_train_meshes"], written["renders_per_mesh"])
    per_mesh = {"train": config.data.renders_per_mesh, "same_view": 1, "novel_view": 1}
    n_renders = count_renders(root / "train" / "render_128" / "color")
    if n_renders == 0 or n_renders % per_mesh["train"]:
        raise CaptureError(f"{root}/train/render_128/color: {n_renders} renders, not a multiple of {per_mesh['train']}")
    n_meshes = n_renders // per_mesh["train"]
    n_train = config.data.train_meshes or min(NARF_TRAIN_MESHES, n_meshes)
    if not 0 < n_train <= n_meshes:
        raise CaptureError(f"{root}: data.train_meshes={n_train}, but the set has {n_meshes} meshes")
    return ThumanSet(root, n_meshes, n_train, per_mesh)


def load_views(dataset: ThumanSet, split: str, meshes: list[int], progress: bool = True):
    """Renders of ``meshes`` in ``split``: views, encoder inputs (N, 3, 128, 128) uint8, PoseBatch (N entries)."""
    per_mesh = dataset.renders_per_mesh[split]
    indices = [per_mesh * m + v for m in meshes for v in range(per_mesh)]

    def load(index):
        main = read_render(dataset.color_dir(split), index, per_mesh)
        second = read_render(dataset.color_dir(split, view2=True), index, per_mesh)
        return (
            view_of_render(main, f"{split}/{index}"),
            np.uint8(second.image * 255 + 0.5).transpose(2, 0, 1),
            main.pose_to_world,
        )

    with ThreadPoolExecutor(2) as pool:
        items = list(tqdm(pool.map(load, indices), total=len(indices), desc=f"loading {split}", disable=not progress))
    if not items:
        raise CaptureError(f"{dataset.color_dir(split)}: no renders for meshes {meshes[:3]}...")
    joints = torch.as_tensor(np.stack([item[2] for item in items]), dtype=torch.float64)
    poses = pose_batch_from_joints(joints).to(torch.float32)
    return [item[0] for item in items], torch.as_tensor(np.stack([item[1] for item in items])), poses


def autoencoder_boxes(body_model: BodyModel, config: FitConfig):
    """Part boxes over rest bodies of varied shape (betas 0 and +-2 along the first two components), padded by the
    config: the union a multi-person set needs (docs/model.md §1)."""
    betas = torch.zeros(5, 10)
    betas[1, 0], betas[2, 0], betas[3, 1], betas[4, 1] = 2.0, -2.0, 2.0, -2.0
    with torch.no_grad():
        rest = body_model.rest_body(betas)
        return body_model.part_boxes([rest], config.model.box_scale_pad, config.model.box_abs_pad)


def build_autoencoder_data(config: FitConfig, device, progress: bool = True) -> AutoencoderData:
    dataset = open_thuman(resolve_thuman(config, quiet=not progress), config)
    views, encoder_inputs, poses = load_views(dataset, "train", list(range(dataset.n_train_meshes)), progress)
    training = TrainingSet(views, list(range(len(views))), poses, device, store_dir=cache_dir() / "views")
    held = dataset.n_train_meshes if dataset.n_train_meshes < dataset.n_meshes else 0

    def validation():
        view, encoder_input, pose = load_views(dataset, "same_view", [held], progress=False)
        return view[0].image, view[0].camera, pose, encoder_input[0]

    return AutoencoderData(
        training,
        autoencoder_boxes(BodyModel(), config),
        list(range(len(views))),
        validation,
        f"{dataset.root}: {len(views)} training renders of {dataset.n_train_meshes} meshes",
        encoder_inputs=encoder_inputs.to(device),
    )


def start(config: FitConfig, run_dir: Path, device, state: dict | None = None, progress: bool = True, processes=None):
    """An AutoencoderTrainer (the CNN baseline: a CnnAutoencoderTrainer) on the config's THUman set; ``state``: the
    checkpoint it resumes. One process (``processes`` is accepted for the kind table's one signature)."""
    data = build_autoencoder_data(config, device, progress)
    return trainer_class(config)(config, run_dir, device, data, state=state, progress=progress)
