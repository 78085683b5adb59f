"""Evaluation protocols (docs/model.md §7): full-image and Neural Body crop metrics of rendered views, and the
report table. The loop over a capture's splits is ``pipelines.runs.subject.evaluation.evaluate_run``."""

from __future__ import annotations

import json
import platform
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import skimage
import torch
from skimage.metrics import structural_similarity

from fitting.config import FitConfig
from fitting.files import atomic_write_text, folder_lock
from narf.cnn_render import render_cnn_image
from narf.fields import CnnBaseline, model_spec
from narf.metrics import mask_l2, psnr, psnr_of
from narf.rays import image_pixels, ray_box_intersect, rays_from_pixels
from narf.renderer import render_image

EVAL_SPLITS = ("same_pose_same_view", "same_pose_novel_view", "novel_pose_same_view", "novel_pose_novel_view")
ALL_SPLITS = (*EVAL_SPLITS, "novel_pose", "novel_view", "all")
#: the error breakdown's inner person pixels lie at least this far (pixels of the evaluated image) inside the mask's
#: edge: beyond the outline's blur and the masks' own error, which reach 1-3 px at the demo's half resolution
INNER_PX = 3
#: the error breakdown's coarse person PSNR compares both images low-passed by a Gaussian of this sigma (pixels of
#: the evaluated image) within the person pixels: wider than the outline's blur, narrower than a limb (about 30 px at
#: the demo's half resolution), so what it keeps is the colour and shading, what it drops the detail and its place
COARSE_PX = 4.0
_SHORT = {
    "same_pose_same_view": "SS",
    "novel_pose_same_view": "NS",
    "same_pose_novel_view": "SN",
    "novel_pose_novel_view": "NN",
    "novel_pose": "novel pose (NB)",
    "novel_view": "novel view (NB)",
    "capture": "capture (another recording)",
}
#: What a report's ``poses`` entry says under its table.
POSE_NOTES = {
    "corrected": "Poses: the same-pose splits show the training frames in the run's corrected poses "
    "(RUN/refined_params); the novel-pose splits keep the capture's, since correcting them would need their images "
    "(docs/model.md §6).",
    "capture": "Poses: the capture's own (the fit did not correct them).",
}


def render_view(field, camera, pose, config: FitConfig, latent: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Full-image render of one (undistorted) camera and one-frame pose at the evaluation sample counts (the CNN
    baseline: its image resampled to the camera's size; no segmentation, zero depth); ``latent`` (1, 2 L) is an
    autoencoder's code."""
    device = next(field.parameters()).device
    K = torch.as_tensor(camera.K, dtype=torch.float32, device=device)
    cam_from_world = torch.as_tensor(camera.cam_from_world, dtype=torch.float32, device=device)
    if isinstance(field, CnnBaseline):
        with torch.no_grad():
            code = None if latent is None else latent.to(device)
            return render_cnn_image(field, K, cam_from_world, camera.height, camera.width, pose, code)
    background = 1.0 if config.data.white_background else 0.0
    return render_image(
        field,
        K,
        cam_from_world,
        camera.height,
        camera.width,
        pose,
        config.render.eval_coarse,
        config.render.eval_fine,
        background,
        config.render.chunk,
        None if latent is None else latent.to(device),
    )


def nb_crop_region(camera, vertices: np.ndarray, pad: float = 0.05) -> np.ndarray:
    """Pixels whose rays hit the world box of the body vertices, padded ``pad`` metres along z (Neural Body)."""
    low, high = vertices.min(0).astype(np.float64), vertices.max(0).astype(np.float64)
    low[2] -= pad
    high[2] += pad
    K = torch.as_tensor(camera.K, dtype=torch.float64)
    origins, dirs = rays_from_pixels(
        K, torch.as_tensor(camera.cam_from_world), image_pixels(camera.height, camera.width, dtype=torch.float64)
    )
    n = origins.shape[0]
    eye = torch.eye(4, dtype=torch.float64).expand(n, 1, 4, 4)
    centre = torch.as_tensor((low + high) / 2)[None]
    half = torch.as_tensor((high - low) / 2)[None]
    _, _, hit = ray_box_intersect(origins, dirs, eye, torch.ones(n, dtype=torch.float64), centre, half)
    return hit.reshape(camera.height, camera.width).numpy()


def ssim(prediction: np.ndarray, target: np.ndarray) -> float:
    """scikit-image SSIM with the project's settings (Gaussian 1.5, population covariance, data range 1)."""
    return float(
        structural_similarity(
            prediction,
            target,
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
            data_range=1.0,
            channel_axis=-1,
        )
    )


def frame_metrics(
    render: dict, gt_rgb: np.ndarray, gt_mask: np.ndarray, region: np.ndarray, bg: float, gt_band=None, unseen=None
) -> dict:
    """Both protocols for one view: full image, and the Neural Body crop (PSNR, Mask L2 over R; SSIM on R's
    bounding rectangle with pixels outside R set to the background); with ``gt_band`` (H, W) bool, also the crop's
    ``breakdown`` (:func:`crop_error_breakdown`, which says what ``unseen`` is)."""
    rgb, mask = render["rgb"], render["mask"]
    t = lambda a: torch.as_tensor(a)  # noqa: E731
    full = {
        "psnr": float(psnr_of(t(rgb), t(gt_rgb))),
        "ssim": ssim(rgb, gt_rgb),
        "mask_l2": float(mask_l2(t(mask), t(gt_mask))),
    }
    if not region.any():
        return {"full": full, "nb_crop": None}
    box = _crop_box(region)
    pred_crop, gt_crop = rgb.copy(), gt_rgb.copy()
    pred_crop[~region], gt_crop[~region] = bg, bg
    crop = {
        "psnr": float(psnr_of(t(rgb), t(gt_rgb), t(region))),
        "ssim": ssim(pred_crop[box], gt_crop[box]),
        "mask_l2": float(mask_l2(t(mask), t(gt_mask), t(region))),
    }
    if gt_band is not None:
        crop["breakdown"] = crop_error_breakdown(rgb, mask, gt_rgb, gt_mask, gt_band, region, unseen)
    return {"full": full, "nb_crop": crop}


def crop_error_breakdown(
    rgb: np.ndarray,
    mask: np.ndarray,
    gt_rgb: np.ndarray,
    gt_mask: np.ndarray,
    gt_band: np.ndarray,
    region: np.ndarray,
    unseen: np.ndarray | None = None,
) -> dict:
    """Where the NB crop's squared error lies (docs/model.md §7, *Error breakdown*).

    Each pixel of R is in one class: ``band`` (the ground truth's boundary band outside its mask, whose colours the
    protocol keeps), else ``silhouette`` (exactly one of the ground-truth mask and the rendered opacity >= 0.5
    covers it), else ``person`` (both cover it), else ``background``.

    Args:
        rgb, gt_rgb: (H, W, 3) in [0, 1]. mask, gt_mask: (H, W) opacity and mask. gt_band, region: (H, W) bool.
        unseen: optional (H, W) bool, the pixels that show a surface of the body no training view saw face-on
            (``pipelines.runs.subject.coverage``).

    Returns:
        ``share_<class>``: the class's part of the summed squared error over R (0 when R has no error);
        ``pixels_<class>``: its part of R's pixels; ``psnr_person``: PSNR over the person pixels (None without any);
        ``psnr_person_inner``: over the person pixels at least ``INNER_PX`` inside the mask's edge (every pixel of
        the (2 INNER_PX + 1)^2 square around them in the mask), the colour away from the outline (None without any);
        ``psnr_person_coarse``: over the person pixels, both images low-passed within them (:func:`masked_blur`,
        sigma ``COARSE_PX``): the error of the colour and shading, without the detail's (None without any);
        ``psnr_person_gain``: over the person pixels once the render's channels are scaled by the gains that fit the
        view best (:func:`best_gains`): what a camera's colour gain could not explain (None without any).
        ``psnr_band_bound``: the crop's PSNR were every pixel outside the band exact, the most a render reaches while
        the band's error stays (None when the band has no error).
        With ``unseen``: ``pixels_unseen``, its part of the person pixels; ``share_unseen``, its part of their
        summed squared error; ``psnr_person_seen`` and ``psnr_person_unseen``, the PSNR over the person pixels
        outside and inside it (None without any).
    """
    inner = cv2.erode((gt_mask >= 0.5).astype(np.uint8), np.ones((2 * INNER_PX + 1,) * 2, np.uint8))[region] > 0
    error = ((rgb - gt_rgb) ** 2).mean(-1)[region]
    band = gt_band[region] & ~(gt_mask[region] >= 0.5)
    gt_person, person = gt_mask[region] >= 0.5, mask[region] >= 0.5
    classes = {
        "person": ~band & gt_person & person,
        "silhouette": ~band & (gt_person != person),
        "band": band,
        "background": ~band & ~gt_person & ~person,
    }
    total = error.sum()
    out = {}
    for name, where in classes.items():
        out[f"share_{name}"] = float(error[where].sum() / total) if total > 0 else 0.0
        out[f"pixels_{name}"] = float(where.mean())
    band_error = error[classes["band"]].sum()
    out["psnr_band_bound"] = float(psnr(torch.as_tensor(band_error / error.size))) if band_error > 0 else None
    person_error = error[classes["person"]]
    out["psnr_person"] = float(psnr(torch.as_tensor(person_error.mean()))) if person_error.size else None
    inner_error = error[classes["person"] & inner]
    out["psnr_person_inner"] = float(psnr(torch.as_tensor(inner_error.mean()))) if inner_error.size else None
    out["psnr_person_coarse"] = out["psnr_person_gain"] = None
    if person_error.size:
        where = np.zeros(region.shape, bool)
        where[region] = classes["person"]
        rendered, truth = rgb[where], gt_rgb[where]
        gain_error = ((rendered * best_gains(rendered, truth) - truth) ** 2).mean()
        out["psnr_person_gain"] = float(psnr(torch.as_tensor(gain_error)))
        coarse = ((masked_blur(rgb, where, COARSE_PX) - masked_blur(gt_rgb, where, COARSE_PX)) ** 2).mean(-1)
        out["psnr_person_coarse"] = float(psnr(torch.as_tensor(coarse[where].mean())))
    if unseen is not None:
        out.update(_seen_and_unseen(person_error, unseen[region][classes["person"]]))
    return out


def _seen_and_unseen(person_error: np.ndarray, unseen: np.ndarray) -> dict:
    """The person pixels' squared errors (N,) split by ``unseen`` (N,) bool (:func:`crop_error_breakdown`)."""
    as_psnr = lambda e: float(psnr(torch.as_tensor(e.mean()))) if e.size else None  # noqa: E731
    total = person_error.sum()
    return {
        "pixels_unseen": float(unseen.mean()) if unseen.size else 0.0,
        "share_unseen": float(person_error[unseen].sum() / total) if total > 0 else 0.0,
        "psnr_person_seen": as_psnr(person_error[~unseen]),
        "psnr_person_unseen": as_psnr(person_error[unseen]),
    }


def best_gains(rendered: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """g_c = sum(r_c t_c) / sum(r_c^2): each channel's gain that brings ``rendered`` (N, 3) closest to ``truth``
    (N, 3) in squared error, as a camera's measured colour (docs/model.md §6, *Measured camera colour*) could apply
    it; 1 for a channel rendered black. Returns (3,)."""
    energy = (rendered**2).sum(0)
    return np.where(energy > 0, (rendered * truth).sum(0) / np.maximum(energy, 1e-300), 1.0)


def masked_blur(image: np.ndarray, where: np.ndarray, sigma: float) -> np.ndarray:
    """G * (I 1_P) / G * 1_P: ``image`` (H, W, C) low-passed by a Gaussian of ``sigma`` pixels over the pixels
    ``where`` (H, W) bool alone (normalised convolution), so that nothing outside them leaks in; a constant over P
    stays that constant. Values outside P are meaningless. Returns (H, W, C) float64."""
    weight = where.astype(np.float64)
    blur = lambda x: cv2.GaussianBlur(x, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)  # noqa: E731
    total = blur(weight)
    return blur(image.astype(np.float64) * weight[..., None]) / np.maximum(total, 1e-12)[..., None]


def _crop_box(region: np.ndarray, min_size: int = 11) -> tuple[slice, slice]:
    """Bounding rectangle of ``region``, grown to at least the SSIM window (11 px for sigma 1.5) where the image
    allows; the added pixels lie outside R and are background in both images."""
    ys, xs = np.nonzero(region)
    bounds = []
    for low, high, size in ((ys.min(), ys.max() + 1, region.shape[0]), (xs.min(), xs.max() + 1, region.shape[1])):
        grow = max(0, min_size - (high - low))
        low = max(0, low - grow // 2)
        high = min(size, max(high, low + min_size))
        bounds.append(slice(max(0, min(low, high - min_size)), high))
    return bounds[0], bounds[1]


def average_metrics(records: list[dict], protocol: str) -> dict:
    """Mean Mask L2, PSNR and SSIM of the views that have ``protocol``; and the mean of each ``breakdown`` entry
    over the views that have one (``psnr_person`` over those with person pixels)."""
    values = [r[protocol] for r in records if r[protocol] is not None]
    if not values:
        return {}
    out = {k: float(np.mean([v[k] for v in values])) for k in ("mask_l2", "psnr", "ssim")}
    breakdowns = [v["breakdown"] for v in values if "breakdown" in v]
    if breakdowns:
        keys = breakdowns[0].keys()
        means = {k: [b[k] for b in breakdowns if b[k] is not None] for k in keys}
        out["breakdown"] = {k: float(np.mean(v)) if v else None for k, v in means.items()}
    return out


def library_versions() -> dict:
    return {
        "scikit-image": skimage.__version__,
        "opencv": cv2.__version__,
        "torch": torch.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
    }


def spread(items: list, limit: int | None) -> list:
    if not limit or len(items) <= limit:
        return items
    return [items[i] for i in np.linspace(0, len(items) - 1, limit).round().astype(int)]


def markdown_table(report: dict) -> str:
    """Supplement layout: one row per protocol, cells Mask L2 (x10^4) / PSNR / SSIM per split."""
    splits = [s for s in (*EVAL_SPLITS, "novel_pose", "novel_view", "capture") if s in report["splits"]]
    size = f"width {report['width']}" if model_spec(report["model"]).rays else f"{report['image_size']}^2 bone maps"
    if report.get("encoding") == "grid":
        size += ", part grids"
    if report.get("shading"):
        size += ", shading"
    if model_spec(report["model"]).rays and "samples" in report:
        size += ", {} + {} samples a ray".format(*report["samples"])
    lines = [
        f"# {report['model']} ({size}), step {report['step']}: {report['subject']}",
        "",
        "Cells: Mask L2 (x10^4) / PSNR (dB) / SSIM. SS/NS/SN/NN = same or novel pose x same or novel view.",
        "",
        "| protocol | " + " | ".join(_SHORT[s] for s in splits) + " |",
        "|---|" + "---|" * len(splits),
    ]
    for protocol in ("full", "nb_crop"):
        cells = []
        for split in splits:
            m = report["splits"][split][protocol]
            cells.append(f"{m['mask_l2']:.1f}/{m['psnr']:.2f}/{m['ssim']:.4f}" if m else "-")
        lines.append(f"| {'full image' if protocol == 'full' else 'NB crop'} | " + " | ".join(cells) + " |")
    breakdown_lines = [_breakdown_line(s, report["splits"][s]["nb_crop"].get("breakdown")) for s in splits]
    if any(breakdown_lines):
        lines += ["", "Where the NB crop's squared error lies (docs/model.md §7, *Error breakdown*):", ""]
        lines += [f"* {line}" for line in breakdown_lines if line]
    for split in splits:
        if mesh := report["splits"][split].get("mesh"):
            lines += [
                "",
                f"Surface ({_SHORT[split]}, {len(mesh['frames'])} frames, marching cubes at {mesh['resolution']} "
                f"samples, level {mesh['level']:g}): distance to the true surface mean {mesh['mean_mm']:.1f} mm, "
                f"95th percentile {mesh['p95_mm']:.1f} mm; normal consistency {mesh['normal_consistency']:.3f}",
            ]
    if "capture" in report["splits"]:
        other = report["splits"]["capture"]
        lines += ["", f"Another capture: {other['capture']} (every frame a novel pose, every camera, its own poses)."]
    if report.get("poses") in POSE_NOTES:
        lines += ["", POSE_NOTES[report["poses"]]]
    versions = ", ".join(f"{k} {v}" for k, v in report["versions"].items())
    lines += [
        "",
        "Views per split: " + ", ".join(_views(_SHORT[s], report["splits"][s]) for s in splits),
        f"Versions: {versions}",
        "",
    ]
    return "\n".join(lines)


def _views(name: str, split: dict) -> str:
    """'SS 12 (frame step 6)': a split's view count and, where the report records it, every how many frames."""
    step = split.get("frame_step")
    return f"{name} {split['n_views']}" + (f" (frame step {step})" if step else "")


def _breakdown_line(split: str, breakdown: dict | None) -> str | None:
    if not breakdown:
        return None
    share = lambda k: f"{100 * breakdown[f'share_{k}']:.0f} %"  # noqa: E731
    pixels = lambda k: f"{100 * breakdown[f'pixels_{k}']:.1f} %"  # noqa: E731
    dB = lambda k: "-" if breakdown.get(k) is None else f"{breakdown[k]:.2f} dB"  # noqa: E731
    seen = ""
    if "pixels_unseen" in breakdown:
        seen = (
            f"; surfaces no training view saw face-on: {pixels('unseen')} of the person pixels, {share('unseen')} "
            f"of their error ({dB('psnr_person_seen')} over the person pixels elsewhere, {dB('psnr_person_unseen')} "
            "there)"
        )
    return (
        f"{_SHORT[split]}: person pixels {share('person')} of the error "
        f"({dB('psnr_person')} over them, {dB('psnr_person_inner')} {INNER_PX} px or more inside the mask's edge, "
        f"{dB('psnr_person_coarse')} low-passed at {COARSE_PX:g} px, {dB('psnr_person_gain')} with the view's best "
        f"colour gains, {pixels('person')} of the crop); silhouette "
        f"disagreement {share('silhouette')} ({pixels('silhouette')} of the crop); the mask's boundary band "
        f"{share('band')} ({pixels('band')}; the crop at {dB('psnr_band_bound')} were every other pixel exact); "
        f"background {share('background')}{seen}"
    )


def evaluate_splits(
    out_dir: Path, splits, score: Callable[[str], dict], header: Callable[[], dict], markdown: Callable[[dict], str]
) -> dict:
    """The evaluation skeleton every run kind shares: ``out_dir/metrics.json`` is read (the results of splits not
    evaluated now are kept), ``score(split)`` fills each split, ``header()`` adds what the run is (then the library
    versions), and ``metrics.json`` and ``metrics.md`` (``markdown(report)``) are written atomically. One evaluation
    of a run at a time (``fitting.files.folder_lock`` on ``out_dir``)."""
    with folder_lock(Path(out_dir)):
        metrics_path = Path(out_dir) / "metrics.json"
        report = json.loads(metrics_path.read_text()) if metrics_path.is_file() else {"splits": {}}
        for split in splits:
            report["splits"][split] = score(split)
        report.update({**header(), "versions": library_versions()})
        write_report(out_dir, report, markdown(report))
    return report


def write_report(out_dir: Path, report: dict, markdown: str) -> None:
    """``metrics.json`` and ``metrics.md`` into ``out_dir``, each atomically."""
    atomic_write_text(Path(out_dir) / "metrics.json", json.dumps(report, indent=1))
    atomic_write_text(Path(out_dir) / "metrics.md", markdown)
