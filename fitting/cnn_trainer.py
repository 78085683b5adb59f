"""Image-space training of the CNN baseline (docs/model.md §4): whole training views resampled to the network's
square size, bone maps rasterised per view, colour + mask MSE (the mask loss skips the boundary band).

Shares the loop, checkpoints, log and validation renders of ``fitting.trainer.Trainer``; only the batch and
the loss differ. "rays/s" in its log counts output pixels. ``CnnAutoencoderTrainer`` adds the autoencoder's image
encoder (``fitting.autoencoder``)."""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F

from fitting.autoencoder import AutoencoderTrainer, encode
from fitting.config import FitConfig
from fitting.corrections import camera_response
from fitting.data import FitData
from fitting.trainer import Trainer
from narf.cnn_render import cnn_inputs


class CnnTrainer(Trainer):
    """A Trainer for the CNN baseline; ``data.training.poses`` must carry ``world_from_joint``."""

    def __init__(
        self,
        config: FitConfig,
        run_dir: Path,
        device: torch.device,
        data: FitData,
        state: dict | None = None,
        progress: bool = True,
    ):
        super().__init__(config, run_dir, device, data, state, progress)
        if self.views.poses.world_from_joint is None:
            raise ValueError("the CNN baseline needs every training pose's world_from_joint")
        size = config.model.image_size
        self.rays_per_step = config.train.images_per_step * size * size
        rgb, mask, weight = [], [], []
        for index in range(len(self.views)):  # one view at a time: only the network-size copies stay in memory
            image, silhouette, band = (torch.as_tensor(a)[None].float() for a in self.views.full_view(index))
            rgb.append(F.interpolate(image.permute(0, 3, 1, 2) / 255.0, size=(size, size), mode="area")[0])
            mask.append(F.interpolate(silhouette[None], size=(size, size), mode="area")[0, 0])
            weight.append(F.interpolate(band[None], size=(size, size), mode="area")[0, 0] == 0)
        self.rgb, self.mask, self.mask_weight = (torch.stack(a).to(device, torch.float16) for a in (rgb, mask, weight))

    def train_step(self) -> tuple[float, float]:
        chosen = self._choose_images()
        return self.optimise(*self.image_loss(chosen))

    def _choose_images(self) -> torch.Tensor:
        n = self.config.train.images_per_step
        return torch.randint(0, len(self.views), (n,), generator=self.generator).to(self.device)

    def image_loss(self, chosen: torch.Tensor, latent: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(loss, colour MSE) of the training images ``chosen`` (B,): colour MSE + lambda_mask masked mask MSE;
        ``latent`` (B, 2 L): the autoencoder's codes of those images."""
        t, data = self.config.train, self.views
        joints = data.poses.world_from_joint[data.frame_of_image[chosen]]
        maps, bones = cnn_inputs(
            joints, data.cam_from_world[chosen], data.Ks[chosen], data.height, data.width, self.config.model.image_size
        )
        rgb, mask = self.field(maps, bones, latent)
        if self.fit_data.camera_gains is not None:  # each training camera's measured colour (docs/model.md §6)
            gains = self.fit_data.camera_gains.to(rgb)[data.camera_of_image[chosen]][:, :, None, None]
            background = 1.0 if self.config.data.white_background else 0.0
            rgb = camera_response(rgb.movedim(1, -1), mask, gains.movedim(1, -1), background).movedim(-1, 1)
        colour = (rgb - self.rgb[chosen].float()).pow(2).mean()
        weight = self.mask_weight[chosen].float()
        mask_term = (weight * (mask - self.mask[chosen].float()).pow(2)).sum() / weight.sum().clamp_min(1)
        return colour + t.mask_weight * mask_term, colour


class CnnAutoencoderTrainer(CnnTrainer, AutoencoderTrainer):
    """The CNN baseline as an autoencoder (docs/model.md §4): the image encoder's code of each training image's
    encoder input conditions the CNN; encoder and CNN train together, checkpointed as an autoencoder run."""

    def train_step(self) -> tuple[float, float]:
        chosen = self._choose_images()
        latent = encode(self.encoder, self.encoder_inputs[chosen])
        return self.optimise(*self.image_loss(chosen, latent))
