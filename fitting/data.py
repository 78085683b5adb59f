"""Training data: training views (on disk, ``fitting.view_store``), per-frame poses, part boxes and mask-guided
ray batches.

Built by ``pipelines.runs.*.session`` from views they load; this module reads no capture files."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from fitting.corrections import CapturePoses
from fitting.view_store import BAND_BIT, POOL_BACKGROUND, POOL_BITS, POOL_BODY, POOL_BORDER, ViewStore
from narf.fields.common import PoseBatch


@dataclass
class RayBatch:
    """origins, dirs (R, 3); frames (R,) index into the pose batch; rgb (R, 3), mask (R,), mask_weight (R,)
    (0 on the 5-px boundary band, skipped by the mask loss); cameras (R,) the training camera of each ray's view."""

    origins: torch.Tensor
    dirs: torch.Tensor
    frames: torch.Tensor
    rgb: torch.Tensor
    mask: torch.Tensor
    mask_weight: torch.Tensor
    cameras: torch.Tensor

    def take(self, index) -> RayBatch:
        """The rays ``index`` (a slice or an index tensor) of the batch."""
        return RayBatch(*(getattr(self, name)[index] for name in self.__dataclass_fields__))


class TrainingSet:
    """Training views in a disk-backed store (``fitting.view_store``), with their cameras, poses and pixel pools.

    Each view is stored once, as uint8 and cropped to its sampling box; a step reads back only the views it draws,
    so memory does not grow with the number of views.

    Args:
        views: loaded views, consumed one at a time (a generator will do): ``image`` (H, W, 3) float in [0, 1],
            ``mask`` (H, W), ``band`` (H, W) bool, optionally ``unknown`` (H, W) bool or None, and ``camera`` (``K``,
            ``cam_from_world``), e.g. ``pipelines.datasets.zju_mocap.Frame``. Views may differ in size.
        frame_of_view: index of each view's frame in ``poses``.
        poses: PoseBatch of the training frames.
        device: where rays and targets are sent.
        store_dir: folder of the store's anonymous file (the system's temporary folder by default).
        camera_of_view: index of each view's training camera (0..C-1; all 0 when not given), for per-camera colour.
    """

    def __init__(self, views, frame_of_view: list[int], poses: PoseBatch, device, store_dir=None, camera_of_view=None):
        self.device = device
        self.poses = poses.to(device)
        self.store = ViewStore(store_dir)
        Ks, cam_from_world = [], []
        for view in views:
            image = (view.image * 255 + 0.5).astype(np.uint8)
            unknown = getattr(view, "unknown", None)  # pixels whose owner is unknown: no ray is drawn there
            self.store.add(image, np.asarray(view.mask) > 0.5, np.asarray(view.band, bool), unknown)
            Ks.append(view.camera.K)
            cam_from_world.append(view.camera.cam_from_world)
        if not Ks:
            raise ValueError("no training views")
        # the largest view's size: the CNN baseline's full views are padded to it (bottom and right)
        self.height = max(self.store.size(i)[0] for i in range(len(self.store)))
        self.width = max(self.store.size(i)[1] for i in range(len(self.store)))
        self.Ks = torch.as_tensor(np.stack(Ks), dtype=torch.float32).to(device)
        self.cam_from_world = torch.as_tensor(np.stack(cam_from_world), dtype=torch.float32).to(device)
        self.frame_of_image = torch.as_tensor(frame_of_view, dtype=torch.long, device=device)
        if len(self.frame_of_image) != len(self.store):
            raise ValueError(f"{len(self.store)} views but {len(self.frame_of_image)} frame indices")
        cameras = [0] * len(self.store) if camera_of_view is None else list(camera_of_view)
        self.camera_of_image = torch.as_tensor(cameras, dtype=torch.long, device=device)
        if len(self.camera_of_image) != len(self.store):
            raise ValueError(f"{len(self.store)} views but {len(self.camera_of_image)} camera indices")
        self.n_cameras = int(self.camera_of_image.max()) + 1

    def __len__(self) -> int:
        return len(self.store)

    def full_view(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """View ``index`` padded to (height, width): image (height, width, 3) uint8, mask and band bool."""
        image, mask, band = self.store.full(index)
        pad = ((0, self.height - mask.shape[0]), (0, self.width - mask.shape[1]))
        return np.pad(image, (*pad, (0, 0))), np.pad(mask, pad), np.pad(band, pad)

    def sample(
        self,
        n_images: int,
        rays_per_image: int,
        body_fraction: float,
        border_fraction: float,
        generator: torch.Generator,
        views_per_frame: int = 1,
    ) -> RayBatch:
        """Draw ``n_images`` images and mask-guided pixels from each (body, border ring, background in the box); an
        empty pool draws from the body pool, and an image with no body pixel from its whole box. ``views_per_frame``
        k > 1: the images are k views each of n_images / k frames (:meth:`choose_images`)."""
        chosen = self.choose_images(n_images, views_per_frame, generator)
        return self.sample_images(chosen, rays_per_image, body_fraction, border_fraction, generator)

    def sample_images(
        self,
        chosen: list[int],
        rays_per_image: int,
        body_fraction: float,
        border_fraction: float,
        generator: torch.Generator,
    ) -> RayBatch:
        """Mask-guided pixels of the images ``chosen``, as :meth:`sample` draws them (by :func:`pool_pixels`)."""
        n_body = int(round(rays_per_image * body_fraction))
        n_border = int(round(rays_per_image * border_fraction))
        counts = (n_body, n_border, rays_per_image - n_body - n_border)
        images, rows, cols, rgb, labels = [], [], [], [], []
        for image in chosen:
            crop, crop_labels = self.store.read(image)
            y0, x0, _, width = self.store.box(image)
            pixels = np.concatenate(pool_pixels(crop_labels, counts, generator))
            v, u = pixels // width, pixels % width
            rows.append(v + y0)
            cols.append(u + x0)
            rgb.append(crop[v, u])
            labels.append(crop_labels[v, u])
            images.append(np.full(len(pixels), image))
        labels = torch.as_tensor(np.concatenate(labels))
        targets = (
            torch.as_tensor(np.concatenate(rgb)).float() / 255.0,
            ((labels & POOL_BITS) == POOL_BODY).float(),
            ((labels & BAND_BIT) == 0).float(),
        )
        pixels = [torch.as_tensor(np.concatenate(a), dtype=torch.long) for a in (images, rows, cols)]
        return self.rays(*(a.to(self.device) for a in pixels), *(t.to(self.device) for t in targets))

    def choose_images(self, n_images: int, views_per_frame: int, generator: torch.Generator) -> list[int]:
        """``n_images`` training images drawn uniformly (``views_per_frame`` 1), or ``n_images // k`` frames drawn
        uniformly and k of each frame's views without repeats (as many as it has when fewer), so that a step sees
        each of its frames from several cameras: a pose correction then gets one gradient from every side."""
        if views_per_frame <= 1:
            return torch.randint(0, len(self), (n_images,), generator=generator).tolist()
        if not hasattr(self, "_views_of_frame"):
            frames = self.frame_of_image.cpu().numpy()
            self._views_of_frame = [np.flatnonzero(frames == f) for f in np.unique(frames)]
        groups = self._views_of_frame
        picked = torch.randint(0, len(groups), (max(n_images // views_per_frame, 1),), generator=generator).tolist()
        chosen = []
        for group in (groups[i] for i in picked):
            chosen += group[torch.randperm(len(group), generator=generator)[:views_per_frame].numpy()].tolist()
        return chosen

    def rays(self, images, rows, cols, rgb, mask, mask_weight) -> RayBatch:
        """Rays through pixels (``rows``, ``cols``) of training ``images`` (R,) each, with their targets."""
        homogeneous = torch.stack([cols.float(), rows.float(), torch.ones_like(cols, dtype=torch.float32)], dim=-1)
        dirs_cam = torch.linalg.solve(self.Ks[images], homogeneous[..., None])[..., 0]
        rotation = self.cam_from_world[images, :3, :3]
        dirs = (rotation.transpose(1, 2) @ dirs_cam[..., None])[..., 0]
        dirs = dirs / dirs.norm(dim=-1, keepdim=True)
        origins = -(rotation.transpose(1, 2) @ self.cam_from_world[images, :3, 3:4])[..., 0]
        return RayBatch(
            origins, dirs, self.frame_of_image[images], rgb, mask, mask_weight, self.camera_of_image[images]
        )


#: candidates a drawn ray of :func:`pool_pixels` (8 a ray, and 64 more): at the default shares (70 / 20 / 10 % of the
#: rays) a pool a twentieth of the crop, as the border ring's least on the real demo, expects 2.3 times its rays
CANDIDATES_PER_RAY, EXTRA_CANDIDATES = 8, 64
POOLS = (POOL_BODY, POOL_BORDER, POOL_BACKGROUND)


def pool_pixels_exact(labels: np.ndarray, counts: tuple[int, int, int], generator: torch.Generator) -> list:
    """Flat pixel indices into ``labels`` (h, w) uint8 (``fitting.view_store``), ``counts`` (body, border,
    background) drawn uniformly with replacement from each pool, each pool listed in full first: the reference
    of :func:`pool_pixels`. An empty pool draws from the body pool, and a crop with no body pixel from all of it.

    Returns:
        the drawn indices of each pool with a count, (count,) int64 each.
    """
    pool_of = labels.reshape(-1) & POOL_BITS
    pools = [np.flatnonzero(pool_of == pool) for pool in POOLS]
    drawn = []
    for pool, count in zip(pools, counts):
        if count == 0:
            continue
        pool = pool if pool.size else pools[0]
        if pool.size == 0:
            pool = np.arange(pool_of.size)
        drawn.append(pool[torch.randint(0, pool.size, (count,), generator=generator).numpy()])
    return drawn


def pool_pixels(labels: np.ndarray, counts: tuple[int, int, int], generator: torch.Generator) -> list:
    """:func:`pool_pixels_exact`'s draws without listing the pools: ``CANDIDATES_PER_RAY`` pixels a ray (and
    ``EXTRA_CANDIDATES``) drawn uniformly over the crop, each pool taking its first hits in their order. Given the
    candidates' labels, a pool's hits are independent and uniform over it, so the draws have the reference's
    distribution; a pool with fewer hits than its count (small, empty) is drawn by the reference instead.
    Arguments and result as :func:`pool_pixels_exact`; its cost is the crop's size there, the rays' here."""
    flat = labels.reshape(-1)
    n_candidates = CANDIDATES_PER_RAY * sum(counts) + EXTRA_CANDIDATES
    candidates = torch.randint(0, flat.size, (n_candidates,), generator=generator).numpy()
    pool_of = flat[candidates] & POOL_BITS
    drawn = []
    for pool, count in zip(POOLS, counts):
        if count == 0:
            continue
        hits = candidates[pool_of == pool][:count]
        if len(hits) < count:  # a pool too small for the candidates: the reference draws every pool again
            return pool_pixels_exact(labels, counts, generator)
        drawn.append(hits)
    return drawn


@dataclass
class OutlineRays:
    """Rays of virtual cameras through the band along the outline of a training frame's body (docs/model.md §6,
    *The bodies' outline from unseen views*): origins and unit dirs (N, 3), frames (N,) long indices into the
    training poses, and inside (N,) 1.0 where the ray meets the body, 0.0 where it passes beside it."""

    origins: torch.Tensor
    dirs: torch.Tensor
    frames: torch.Tensor
    inside: torch.Tensor

    def to(self, device) -> OutlineRays:
        return OutlineRays(*(t.to(device) for t in (self.origins, self.dirs, self.frames, self.inside)))


@dataclass
class FitData:
    """Everything a Trainer needs from a capture.

    Attributes:
        training: the training views.
        boxes: part box centres and half-extents (P, 3) each, fitted on the training poses.
        frames: capture frame index of each training pose.
        validation: callable returning (ground-truth image, camera, one-frame PoseBatch) of a held-out view,
            or None.
        description: one line naming the capture, for logs.
        capture_poses: the training frames' body parameters, which pose correction starts from (None: the data
            has none, e.g. posed joint frames only).
        validation_frame: the training-frame index of the validation view's pose (None: not a training frame).
        provenance: what the fit depends on outside its config (the body model's record), saved in the checkpoint.
        selection: the views of the training frames held back to choose the step kept (``fitting.selection``), or
            None.
        camera_gains: (C, 3) the measured colour gain of each training camera (``training``'s camera indices), or
            None (docs/model.md §6, *Measured camera colour*).
        shells: (P, N, N, N) bool, the part boxes' shells (docs/model.md §1, *Body shells*), or None: whole boxes.
        mirrored_poses: the training frames' bodies in their mirror-image poses (docs/model.md §6, *Left-right
            symmetry*), on the training device, or None: the symmetry term is off.
        outline_rays: the bodies' outlines from virtual cameras, on the training device, or None: the outline term is
            off.
    """

    training: TrainingSet
    boxes: tuple[torch.Tensor, torch.Tensor]
    frames: list[int]
    validation: Callable | None = None
    description: str = ""
    capture_poses: CapturePoses | None = None
    validation_frame: int | None = None
    provenance: dict = field(default_factory=dict)
    selection: TrainingSet | None = None
    camera_gains: torch.Tensor | None = None
    shells: torch.Tensor | None = None
    mirrored_poses: PoseBatch | None = None
    outline_rays: OutlineRays | None = None
