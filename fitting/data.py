"""Training data: the protocol's training views in memory, per-frame poses, part boxes, mask-guided rays."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from tqdm import tqdm

from narf.fields.common import PoseBatch
from pipelines.body_model import BodyModel, pose_batch
from pipelines.capture import ZjuCapture

BORDER_PX = 11  # width of the dilation that defines the border band around the silhouette


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


def poses_for_frames(capture: ZjuCapture, body_model: BodyModel, frames: list[int]):
    """PoseBatch, posed bodies and betas (F, 10) of capture frames, from their SMPL parameters."""
    params = [capture.params(f) for f in frames]
    stack = [torch.as_tensor(np.stack([getattr(p, k) for p in params])) for k in ("poses", "rh", "th", "shapes")]
    with torch.no_grad():
        bodies = body_model.pose_zju(*stack)
    return pose_batch(bodies), bodies, stack[3]


def fit_boxes(body_model: BodyModel, bodies, shapes: torch.Tensor, n_frames: int, scale_pad: float, abs_pad: float):
    """Part boxes over the rest pose and up to ``n_frames`` evenly spaced training frames (model.md §1)."""
    count = bodies.vertices.shape[0]
    pick = torch.as_tensor(np.unique(np.linspace(0, count - 1, min(n_frames, count)).astype(int)))
    subset = type(bodies)(*(getattr(bodies, k)[pick] for k in bodies.__dataclass_fields__))
    with torch.no_grad():
        rest = body_model.rest_body(shapes[:1])
        return body_model.part_boxes([rest, subset], scale_pad, abs_pad)


class TrainingSet:
    """All training (frame, view) images of a protocol, kept as uint8 on ``device``.

    Args:
        capture: the subject. frames / views: training frames and camera indices. poses: PoseBatch of ``frames``.
        device: where images and rays live.
    """

    def __init__(self, capture: ZjuCapture, frames: list[int], views: list[int], poses: PoseBatch, device,
                 progress: bool = True):  # fmt: skip
        items = [(i, f, c) for i, f in enumerate(frames) for c in views]
        with ThreadPoolExecutor(2) as pool:
            loaded = list(tqdm(pool.map(lambda item: capture.load_frame(item[1], item[2]), items), total=len(items),
                               desc="loading training views", unit="image", disable=not progress))  # fmt: skip
        self.device = device
        self.poses = poses.to(device)
        self.height, self.width = loaded[0].image.shape[:2]
        self.images = torch.as_tensor(np.stack([(f.image * 255 + 0.5).astype(np.uint8) for f in loaded])).to(device)
        self.masks = torch.as_tensor(np.stack([f.mask > 0.5 for f in loaded])).to(device)
        self.bands = torch.as_tensor(np.stack([f.band for f in loaded])).to(device)
        self.Ks = torch.as_tensor(np.stack([f.camera.K for f in loaded]), dtype=torch.float32).to(device)
        self.cam_from_world = torch.as_tensor(np.stack([f.camera.cam_from_world for f in loaded]),
                                              dtype=torch.float32).to(device)  # fmt: skip
        self.frame_of_image = torch.as_tensor([i for i, _, _ in items], dtype=torch.long, device=device)
        self.pools = [self._pools(f.mask > 0.5) for f in loaded]

    def __len__(self) -> int:
        return self.images.shape[0]

    def _pools(self, mask: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Flat pixel indices of body, border band and background inside the padded silhouette box."""
        mask_u8 = mask.astype(np.uint8)
        dilated = cv2.dilate(mask_u8, np.ones((BORDER_PX, BORDER_PX), np.uint8)) > 0
        border = dilated & ~mask
        ys, xs = np.nonzero(dilated) if dilated.any() else (np.array([0, self.height - 1]), np.array([0, self.width - 1]))
        pad_y, pad_x = int(0.1 * (ys.max() - ys.min() + 1)), int(0.1 * (xs.max() - xs.min() + 1))
        box = np.zeros_like(mask)
        box[max(ys.min() - pad_y, 0) : ys.max() + pad_y + 1, max(xs.min() - pad_x, 0) : xs.max() + pad_x + 1] = True
        background = box & ~dilated
        as_index = lambda m: torch.as_tensor(np.flatnonzero(m), dtype=torch.long, device=self.device)  # noqa: E731
        body = as_index(mask)
        return body, as_index(border), as_index(background)

    def sample(self, n_images: int, rays_per_image: int, body_fraction: float, border_fraction: float,
               generator: torch.Generator) -> RayBatch:  # fmt: skip
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
