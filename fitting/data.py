"""Training data in memory: training views, per-frame poses, part boxes and mask-guided ray batches.

Built by ``pipelines.runs.subject.session`` from a capture; this module reads no files."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from narf.fields.common import PoseBatch

BORDER_PX = 11  # side of the square dilation kernel: the border band is the 5-px ring around the silhouette


@dataclass
class RayBatch:
    """origins, dirs (R, 3); frames (R,) index into the pose batch; rgb (R, 3), mask (R,), mask_weight (R,)
    (0 on the 5-px boundary band, skipped by the mask loss)."""

    origins: torch.Tensor
    dirs: torch.Tensor
    frames: torch.Tensor
    rgb: torch.Tensor
    mask: torch.Tensor
    mask_weight: torch.Tensor

    def take(self, index) -> RayBatch:
        """The rays ``index`` (a slice or an index tensor) of the batch."""
        return RayBatch(*(getattr(self, name)[index] for name in self.__dataclass_fields__))


class TrainingSet:
    """Training images kept as uint8 on ``device``, with their cameras, poses and sampling pools.

    Args:
        views: loaded views with ``image`` (H, W, 3) float in [0, 1], ``mask`` (H, W), ``band`` (H, W) bool and
            ``camera`` (``K``, ``cam_from_world``), e.g. ``pipelines.zju_mocap.Frame``.
        frame_of_view: index of each view's frame in ``poses``.
        poses: PoseBatch of the training frames.
        device: where images and rays live.
    """

    def __init__(self, views: list, frame_of_view: list[int], poses: PoseBatch, device):
        self.device = device
        self.poses = poses.to(device)
        # Cameras may differ in image size: every view is stored at the largest size, padded at the bottom and
        # right, and its sampling pools stay inside its own pixels.
        self.height = max(v.image.shape[0] for v in views)
        self.width = max(v.image.shape[1] for v in views)
        self.images = torch.as_tensor(np.stack([self._padded((v.image * 255 + 0.5).astype(np.uint8)) for v in views]))
        self.images = self.images.to(device)
        self.masks = torch.as_tensor(np.stack([self._padded(v.mask > 0.5) for v in views])).to(device)
        self.bands = torch.as_tensor(np.stack([self._padded(v.band) for v in views])).to(device)
        self.Ks = torch.as_tensor(np.stack([v.camera.K for v in views]), dtype=torch.float32).to(device)
        self.cam_from_world = torch.as_tensor(
            np.stack([v.camera.cam_from_world for v in views]), dtype=torch.float32
        ).to(device)
        self.frame_of_image = torch.as_tensor(frame_of_view, dtype=torch.long, device=device)
        self.pools = [self._pools(v.mask > 0.5) for v in views]

    def __len__(self) -> int:
        return self.images.shape[0]

    def _padded(self, array: np.ndarray) -> np.ndarray:
        """``array`` (h, w, ...) zero-padded to (height, width, ...)."""
        pad = [(0, self.height - array.shape[0]), (0, self.width - array.shape[1])] + [(0, 0)] * (array.ndim - 2)
        return np.pad(array, pad) if any(p[1] for p in pad) else array

    def _pools(self, mask: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Flat pixel indices of body, border band and background inside the padded silhouette box."""
        own_height, own_width = mask.shape
        mask = self._padded(mask)
        mask_u8 = mask.astype(np.uint8)
        dilated = cv2.dilate(mask_u8, np.ones((BORDER_PX, BORDER_PX), np.uint8)) > 0
        dilated[own_height:], dilated[:, own_width:] = False, False
        border = dilated & ~mask
        if dilated.any():
            ys, xs = np.nonzero(dilated)
        else:  # an empty mask: the whole image is background
            ys, xs = np.array([0, own_height - 1]), np.array([0, own_width - 1])
        pad_y, pad_x = int(0.1 * (ys.max() - ys.min() + 1)), int(0.1 * (xs.max() - xs.min() + 1))
        box = np.zeros_like(mask)
        box[max(ys.min() - pad_y, 0) : ys.max() + pad_y + 1, max(xs.min() - pad_x, 0) : xs.max() + pad_x + 1] = True
        box[own_height:], box[:, own_width:] = False, False
        background = box & ~dilated
        as_index = lambda m: torch.as_tensor(np.flatnonzero(m), dtype=torch.long, device=self.device)  # noqa: E731
        body = as_index(mask)
        return body, as_index(border), as_index(background)

    def sample(
        self,
        n_images: int,
        rays_per_image: int,
        body_fraction: float,
        border_fraction: float,
        generator: torch.Generator,
    ) -> RayBatch:
        """Draw ``n_images`` images and mask-guided pixels from each (body, border band, background in the box)."""
        chosen = torch.randint(0, len(self), (n_images,), generator=generator).tolist()
        n_body = int(round(rays_per_image * body_fraction))
        n_border = int(round(rays_per_image * border_fraction))
        counts = (n_body, n_border, rays_per_image - n_body - n_border)
        images, pixels = [], []
        for image in chosen:
            for pool, count in zip(self.pools[image], counts):
                if count == 0:
                    continue
                pool = pool if pool.numel() else self.pools[image][0]
                if pool.numel() == 0:
                    pool = torch.arange(self.height * self.width, device=self.device)
                pick = torch.randint(0, pool.numel(), (count,), generator=generator)
                pixels.append(pool[pick.to(pool.device)])
                images.append(torch.full((count,), image, dtype=torch.long, device=self.device))
        return self.rays(torch.cat(images), torch.cat(pixels))

    def rays(self, images: torch.Tensor, flat_pixels: torch.Tensor) -> RayBatch:
        """Rays and targets of given (image, flat pixel index) pairs."""
        v, u = flat_pixels // self.width, flat_pixels % self.width
        homogeneous = torch.stack([u.float(), v.float(), torch.ones_like(u, dtype=torch.float32)], dim=-1)
        dirs_cam = torch.linalg.solve(self.Ks[images], homogeneous[..., None])[..., 0]
        rotation = self.cam_from_world[images, :3, :3]
        dirs = (rotation.transpose(1, 2) @ dirs_cam[..., None])[..., 0]
        dirs = dirs / dirs.norm(dim=-1, keepdim=True)
        origins = -(rotation.transpose(1, 2) @ self.cam_from_world[images, :3, 3:4])[..., 0]
        rgb = self.images[images, v, u].float() / 255.0
        mask = self.masks[images, v, u].float()
        weight = (~self.bands[images, v, u]).float()
        return RayBatch(origins, dirs, self.frame_of_image[images], rgb, mask, weight)


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
    """

    training: TrainingSet
    boxes: tuple[torch.Tensor, torch.Tensor]
    frames: list[int]
    validation: Callable | None = None
    description: str = ""
