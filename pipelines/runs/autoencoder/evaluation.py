"""Evaluate a trained autoencoder (``narf-eval --run RUN`` on an autoencoder run): the supplement's four THUman
splits (the encoder sees a same-distribution ``_view2`` render of the same mesh; supplement §A) and the
cross-dataset transfer to SURREAL, each next to the *mean-code baseline* (the average training code), which
shows what the encoder adds.

``cross_dataset`` encodes frame 0 of every SURREAL clip and reports the reconstruction of that frame, and, beyond
the paper (which shows SURREAL only qualitatively), novel poses: the same code rendered in the poses of later
frames of the clip through the same camera, compared with those frames. SURREAL frames are made right-handed
(flipped, with ``right_handed_view``), cropped square around the body (1.2 x its larger side), resized to 128^2
with the intrinsics adjusted, and put on black through ``_segm.mat`` as the THUman renders are. With
``refine_steps`` (``narf-eval --refine-steps N``), a third code joins them: the encoder's code refined by N steps of
the training loss on the encoded frame (``fitting.autoencoder.refine_code``; the field is fixed). Its reconstruction
row fits the scored image itself; its novel-pose row is the fair measure of what refinement adds.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import imageio.v2 as imageio
import numpy as np
import torch
from tqdm import tqdm

from fitting.autoencoder import build_encoder, encode, refine_code
from fitting.config import FitConfig
from fitting.evaluate import average_metrics, evaluate_splits, render_view, spread, ssim
from fitting.fitted import SavedRun, load_fitted, load_weights, read_run, run_folder
from fitting.plots import grid, save_png, to_numpy
from narf.fields import model_spec
from narf.metrics import mask_l2, psnr_of
from pipelines.body.model import BodyModel, pose_batch_from_joints
from pipelines.body.surreal import pose_surreal
from pipelines.datasets.camera import Camera
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.subjects import data_root, stand_in_notice
from pipelines.datasets.surreal import check_clip, read_frame_maps, right_handed_view
from pipelines.runs.autoencoder.session import ThumanSet, ThumanView, load_views, open_thuman, resolve_thuman
from pipelines.runs.requests import EvalRequest, refuse_options
from pipelines.synthetic.surreal import SurrealSynthConfig, generate_surreal, is_surreal_complete

#: the square crop's side over the body's larger side in a SURREAL frame (docs/model.md §4, SURREAL inputs)
SURREAL_CROP_MARGIN = 1.2

THUMAN_SPLITS = {
    "same_pose_same_view": ("same_view", False),
    "novel_pose_same_view": ("same_view", True),
    "same_pose_novel_view": ("novel_view", False),
    "novel_pose_novel_view": ("novel_view", True),
}
AUTOENCODER_SPLITS = (*THUMAN_SPLITS, "cross_dataset")
_SHORT = {"same_pose_same_view": "SS", "novel_pose_same_view": "NS", "same_pose_novel_view": "SN"}
_SHORT |= {"novel_pose_novel_view": "NN", "cross_dataset": "SURREAL"}
CROP_SIZE = 128


@dataclass
class AutoencoderRun:
    """A trained autoencoder ready to evaluate: config, field and encoder (eval mode), its THUman set, step."""

    config: FitConfig
    field: torch.nn.Module
    encoder: torch.nn.Module
    dataset: ThumanSet
    step: int


def load_autoencoder_run(run: Path | SavedRun, device="cpu") -> AutoencoderRun:
    """Load an autoencoder run (refusing a per-subject fit with a clear error); ``run``: the folder, or its
    checkpoint already read."""
    fitted = load_fitted(run, device, kind="autoencoder")
    config = fitted.config
    encoder = build_encoder(config).to(device)
    load_weights(encoder, fitted.state.get("encoder", {}), run_folder(run), "the image encoder of its config")
    dataset = open_thuman(resolve_thuman(config, quiet=True, generate=False), config)
    return AutoencoderRun(config, fitted.field, encoder.eval(), dataset, fitted.step)


def mean_code(run: AutoencoderRun, device, n_meshes: int = 64) -> torch.Tensor:
    """The average code of the encoder over the _view2 inputs of up to ``n_meshes`` training meshes: (1, 2 L)."""
    meshes = spread(list(range(run.dataset.n_train_meshes)), n_meshes)
    _, inputs, _ = load_views(run.dataset, "same_view", meshes, progress=False)
    with torch.no_grad():
        return encode(run.encoder, inputs.to(device)).mean(dim=0, keepdim=True)


def _metrics(render: dict, image: np.ndarray, mask: np.ndarray) -> dict:
    t = torch.as_tensor
    return {
        "psnr": float(psnr_of(t(render["rgb"]), t(image))),
        "ssim": ssim(render["rgb"], image),
        "mask_l2": float(mask_l2(t(render["mask"]), t(mask))),
    }


def _score(run, view, pose, code, baseline, device) -> tuple[dict, dict, dict]:
    """(metrics with the code, metrics with the mean code, the render with the code) of one view."""
    out = {}
    for name, latent in (("encoded", code), ("mean_code", baseline)):
        with torch.no_grad():
            out[name] = to_numpy(render_view(run.field, view.camera, pose.to(device), run.config, latent))
    return _metrics(out["encoded"], view.image, view.mask), _metrics(out["mean_code"], view.image, view.mask), out


def evaluate_thuman_split(run: AutoencoderRun, split: str, baseline, out_dir: Path, request: EvalRequest) -> dict:
    """One THUman split: each view encoded from its _view2 input and rendered with that code and with the mean
    code (``baseline``); the first ``request.grids`` views also as grids."""
    limit, device, progress, grids = request.limit, request.device, request.progress, request.grids
    folder, novel_pose = THUMAN_SPLITS[split]
    meshes = list(
        range(run.dataset.n_train_meshes, run.dataset.n_meshes) if novel_pose else range(run.dataset.n_train_meshes)
    )
    meshes = spread(meshes, limit)
    if not meshes:
        raise CaptureError(f"{run.dataset.root}: split '{split}' has no meshes (no held-out poses in this set?)")
    views, inputs, poses = load_views(run.dataset, folder, meshes, progress=False)
    records = []
    for i, view in enumerate(tqdm(views, desc=f"eval {split}", unit="view", disable=not progress)):
        with torch.no_grad():
            code = encode(run.encoder, inputs[i : i + 1].to(device))
        encoded, base, renders = _score(run, view, poses.select(torch.tensor([i])), code, baseline, device)
        records.append({"view": view.camera.name, "full": encoded, "mean_code": base})
        if i < grids:
            encoder_image = inputs[i].permute(1, 2, 0).numpy() / 255.0
            row = np.concatenate([encoder_image, grid(view.image, renders["encoded"])], axis=1)
            save_png(out_dir / "grids" / split / f"{i:03d}.png", row)
    return {
        "n_views": len(records),
        "full": average_metrics(records, "full"),
        "mean_code": average_metrics(records, "mean_code"),
        "per_view": records,
    }


def resolve_surreal(root: str | Path | None, quiet: bool = False) -> list[Path]:
    """``_info.mat`` files under a SURREAL folder, else under the synthetic stand-in (generated when missing)."""
    if root is not None and Path(root).is_dir():
        infos = sorted(Path(root).rglob("*_info.mat"))
        if not infos:
            raise CaptureError(f"{root}: no SURREAL clip (*_info.mat) below this folder")
        return infos
    out = data_root(root) / "synthetic" / "surreal"
    if not is_surreal_complete(out):
        if not quiet:
            stand_in_notice(f"no SURREAL folder given; generating the synthetic stand-in at {out}")
        generate_surreal(out, SurrealSynthConfig(), progress=not quiet)
    return sorted(out.rglob("*_info.mat"))


def surreal_view(clip, info_path: Path, frame: int, body_model: BodyModel, video) -> tuple[ThumanView, object]:
    """One SURREAL frame as a right-handed 128^2 view on black (module docstring) and its PoseBatch."""
    rgb = np.asarray(video.get_data(frame), np.float32)[:, ::-1] / 255.0
    segm = read_frame_maps(info_path, frame)[0][:, ::-1]
    if not (segm > 0).any():
        raise CaptureError(f"{info_path}: frame {frame} has an empty segmentation")
    K, cam_from_world = right_handed_view(clip.K, clip.cam_from_world, width=rgb.shape[1])
    ys, xs = np.nonzero(segm)
    side = SURREAL_CROP_MARGIN * max(ys.max() - ys.min() + 1, xs.max() - xs.min() + 1)
    centre = np.array([(xs.min() + xs.max()) / 2, (ys.min() + ys.max()) / 2])
    scale = CROP_SIZE / side
    # pixel centres: u' = (u + 0.5 - x0) s - 0.5, with x0 the crop's left edge
    shift = (0.5 - (centre - side / 2)) * scale - 0.5
    affine = np.array([[scale, 0, shift[0]], [0, scale, shift[1]]])
    mask = (segm > 0).astype(np.float32)
    image = cv2.warpAffine(rgb * mask[..., None], affine, (CROP_SIZE, CROP_SIZE), flags=cv2.INTER_LINEAR)
    mask = cv2.warpAffine(mask, affine, (CROP_SIZE, CROP_SIZE), flags=cv2.INTER_LINEAR)
    K_crop = np.vstack([affine, [0, 0, 1]]) @ K
    camera = Camera(f"{info_path.name}:{frame}", K_crop, np.zeros(5), cam_from_world, CROP_SIZE, CROP_SIZE)
    with torch.no_grad():
        pose = pose_batch_from_joints(pose_surreal(body_model, clip, [frame]).world_from_joint.double()).to(
            torch.float32
        )
    return ThumanView(image, mask, np.zeros(mask.shape, bool), camera), pose


def check_refinable(run: AutoencoderRun, run_dir: Path, refine_steps: int) -> None:
    """Refuse ``refine_steps`` (--refine-steps) where it cannot run: a negative count, the CNN baseline."""
    if refine_steps < 0:
        raise ValueError(f"--refine-steps must be >= 0, got {refine_steps}")
    if refine_steps and not model_spec(run.config.model.name).rays:
        raise ValueError(
            f"{run_dir}: the CNN baseline renders no rays, so its codes cannot be refined (--refine-steps)"
        )


def refined_code(run: AutoencoderRun, code, view: ThumanView, pose, steps: int, device) -> torch.Tensor:
    """``refine_code`` on an input view (its own camera and pose)."""
    t = torch.as_tensor
    camera = view.camera
    return refine_code(
        run.config,
        run.field,
        code,
        t(camera.K),
        t(camera.cam_from_world),
        pose.to(device),
        t(view.image),
        t(view.mask),
        steps,
    )


def evaluate_cross_dataset(run, baseline, out_dir: Path, request: EvalRequest) -> dict:
    """Encode frame 0 of each SURREAL clip (``request.surreal``, default the stand-in); score it and two later frames
    with the code, the mean code and, when ``request.refine_steps`` > 0, the code refined on frame 0
    (``refine_code``)."""
    limit, device, progress, grids = request.limit, request.device, request.progress, request.grids
    surreal_root, refine_steps = request.surreal, request.refine_steps
    body_model = BodyModel()
    infos = spread(resolve_surreal(surreal_root, quiet=not progress), limit)
    records = {"reconstruction": [], "novel_pose": []}
    for c, info in enumerate(tqdm(infos, desc="eval cross_dataset", unit="clip", disable=not progress)):
        clip = check_clip(info)
        with imageio.get_reader(str(info).replace("_info.mat", ".mp4")) as video:
            frames = [0, clip.n_frames // 2, clip.n_frames - 1]
            views = [surreal_view(clip, info, f, body_model, video) for f in frames]
        encoder_input = torch.as_tensor(np.uint8(views[0][0].image * 255 + 0.5).transpose(2, 0, 1))[None]
        with torch.no_grad():
            code = encode(run.encoder, encoder_input.to(device))
        refined = refined_code(run, code, *views[0], refine_steps, device) if refine_steps else None
        row = [views[0][0].image]
        for k, (view, pose) in enumerate(views):
            encoded, base, renders = _score(run, view, pose, code, baseline, device)
            record = {"view": view.camera.name, "full": encoded, "mean_code": base}
            row += [view.image, renders["encoded"]["rgb"]]
            if refined is not None:
                with torch.no_grad():
                    render = to_numpy(render_view(run.field, view.camera, pose.to(device), run.config, refined))
                record["refined"] = _metrics(render, view.image, view.mask)
                row.append(render["rgb"])
            records["reconstruction" if k == 0 else "novel_pose"].append(record)
        if c < grids:
            save_png(
                out_dir / "grids" / "cross_dataset" / f"{info.name.removesuffix('_info.mat')}.png",
                np.concatenate(row, 1),
            )
    result = {}
    for kind, r in records.items():
        result[kind] = {
            "n_views": len(r),
            "full": average_metrics(r, "full"),
            "mean_code": average_metrics(r, "mean_code"),
        }
        if refine_steps:
            result[kind] |= {"refined": average_metrics(r, "refined"), "refine_steps": refine_steps}
        result[kind]["per_view"] = r
    return result


def markdown_autoencoder(report: dict) -> str:
    """Table A layout: rows = the encoder's code and the mean-code baseline; cells Mask L2 / PSNR / SSIM."""
    columns = [(s, report["splits"][s]) for s in THUMAN_SPLITS if s in report["splits"]]
    if "cross_dataset" in report["splits"]:
        cross = report["splits"]["cross_dataset"]
        columns += [("SURREAL recon.", cross["reconstruction"]), ("SURREAL novel pose", cross["novel_pose"])]
    cell = lambda m: f"{m['mask_l2']:.1f}/{m['psnr']:.2f}/{m['ssim']:.4f}" if m else "-"  # noqa: E731
    size = f"width {report['width']}" if model_spec(report["model"]).rays else f"{report['image_size']}^2 bone maps"
    steps = {part.get("refine_steps") for _, part in columns} - {None}
    refined_row = [
        f"| encoder + {n} refinement steps on the input | "
        + " | ".join(cell(part.get("refined")) for _, part in columns)
        + " |"
        for n in steps
    ]
    lines = [
        f"# autoencoder {report['model']} ({size}, latent {report['latent_dim']}), step {report['step']}",
        "",
        "Cells: Mask L2 (x10^4) / PSNR (dB) / SSIM on 128^2 images. SS/NS/SN/NN = same or novel pose x same or "
        "novel view.",
        "",
        "| code | " + " | ".join(_SHORT.get(name, name) for name, _ in columns) + " |",
        "|---|" + "---|" * len(columns),
        "| encoder | " + " | ".join(cell(part["full"]) for _, part in columns) + " |",
        *refined_row,
        "| mean code (baseline) | " + " | ".join(cell(part["mean_code"]) for _, part in columns) + " |",
        "",
        "Views: " + ", ".join(f"{_SHORT.get(name, name)} {part['n_views']}" for name, part in columns),
        "",
    ]
    return "\n".join(lines)


def evaluate_autoencoder_run(run: Path | SavedRun, request: EvalRequest) -> dict:
    """Evaluate ``request.splits`` (THUman's four and/or ``cross_dataset``); update ``RUN/eval/metrics.{json,md}``
    (the kind table's entry point; options of subject runs are refused). ``request.refine_steps`` > 0 adds
    cross_dataset's refined-code row (``refine_code`` on the encoded frame)."""
    saved = read_run(run)
    run_dir, r = saved.run_dir, request
    options = {"--mesh": r.mesh, "--capture": r.capture}
    refuse_options(
        run_dir, "autoencoder", options, "subject runs (an autoencoder run has no true surfaces or captures)"
    )
    subject_only = {"--novel-colour": r.novel_colour, "--samples": r.samples, "--frame-step": r.frame_step}
    refuse_options(run_dir, "autoencoder", subject_only, "subject runs")
    if r.refine_steps and "cross_dataset" not in r.splits:
        raise ValueError(f"{run_dir}: --refine-steps refines SURREAL codes; it needs --split cross_dataset or all")
    loaded = load_autoencoder_run(saved, r.device)
    check_refinable(loaded, run_dir, r.refine_steps)
    out_dir = run_dir / "eval"
    baseline = mean_code(loaded, r.device)

    def score(split: str) -> dict:
        if split == "cross_dataset":
            return evaluate_cross_dataset(loaded, baseline, out_dir, r)
        return evaluate_thuman_split(loaded, split, baseline, out_dir, r)

    def header() -> dict:
        c = loaded.config
        return {
            "run": str(run_dir),
            "kind": "autoencoder",
            "step": loaded.step,
            "model": c.model.name,
            "width": c.model.width,
            "image_size": c.model.image_size,
            "latent_dim": c.model.latent_dim,
            "dataset": str(loaded.dataset.root),
        }

    return evaluate_splits(out_dir, r.splits, score, header, markdown_autoencoder)
