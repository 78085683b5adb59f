"""The CNN baseline (docs/model.md §4): a U-Net from 46 rasterised bone maps to RGB and mask.

Five residual down blocks (128 -> 4 px, at most 256 channels), then two skip decoders
(RGB, mask). Every normalisation is a conditional batch norm whose scale and shift come from the bones'
camera-frame poses (19 x 12 values). Mask = sigmoid(logit - 5). No depth, no segmentation.

As an autoencoder (``latent_dim`` > 0, docs/model.md §4) the code z = [z_s, z_a] of the image encoder joins the
bone poses as the conditioning vector of every normalisation, so one network renders every person.
"""

from __future__ import annotations

import torch
from torch import nn

from narf.bone_maps import N_CHANNELS
from narf.geometry import check_shape

POSE_DIM = 19 * 12
_ENCODER = (32, 64, 128, 256, 256, 256)  # stem width, then the five down blocks
_LOGIT_BOUND = 15.0


class ConditionalBatchNorm(nn.Module):
    """BatchNorm without affine parameters; gamma, beta = Linear(condition) (gamma around 1)."""

    def __init__(self, channels: int, condition_dim: int = POSE_DIM):
        super().__init__()
        self.norm = nn.BatchNorm2d(channels, affine=False)
        self.affine = nn.Linear(condition_dim, 2 * channels)
        nn.init.zeros_(self.affine.weight)
        nn.init.zeros_(self.affine.bias)

    def forward(self, x: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
        gamma, beta = self.affine(pose).chunk(2, dim=-1)
        return self.norm(x) * (1 + gamma[..., None, None]) + beta[..., None, None]


class _ResBlock(nn.Module):
    """CBN-ReLU-conv3-CBN-ReLU-conv3 + 1x1 skip; optional 2x average-pool."""

    def __init__(self, c_in: int, c_out: int, down: bool, condition_dim: int):
        super().__init__()
        self.norm1, self.conv1 = ConditionalBatchNorm(c_in, condition_dim), nn.Conv2d(c_in, c_out, 3, padding=1)
        self.norm2, self.conv2 = ConditionalBatchNorm(c_out, condition_dim), nn.Conv2d(c_out, c_out, 3, padding=1)
        self.skip = nn.Conv2d(c_in, c_out, 1) if c_in != c_out else nn.Identity()
        self.pool = nn.AvgPool2d(2) if down else nn.Identity()

    def forward(self, x: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
        h = self.conv1(torch.relu(self.norm1(x, pose)))
        h = self.conv2(torch.relu(self.norm2(h, pose)))
        return self.pool(h + self.skip(x))


class _Decoder(nn.Module):
    """Upsample 4 -> 128 px; each level concatenates the encoder features of its resolution."""

    def __init__(self, out_channels: int, condition_dim: int):
        super().__init__()
        widths = _ENCODER[::-1]  # 256 (4 px) ... 32 (128 px)
        self.blocks = nn.ModuleList(
            _ResBlock(widths[k] + widths[k + 1], widths[k + 1], False, condition_dim) for k in range(len(widths) - 1)
        )
        self.out = nn.Conv2d(widths[-1], out_channels, 3, padding=1)

    def forward(self, bottom: torch.Tensor, skips: list[torch.Tensor], pose: torch.Tensor) -> torch.Tensor:
        h = bottom
        for block, skip in zip(self.blocks, skips[::-1][1:]):
            h = nn.functional.interpolate(h, scale_factor=2, mode="nearest")
            h = block(torch.cat([h, skip], dim=1), pose)
        return self.out(torch.relu(h))


class CnnBaseline(nn.Module):
    """Bone maps (B, 46, S, S), bone poses (B, 228) and, as an autoencoder, codes (B, 2 L) -> RGB (B, 3, S, S) in
    [0, 1] and mask (B, S, S); S = ``image_size`` (paper 128, a multiple of 32)."""

    def __init__(self, image_size: int = 128, latent_dim: int = 0):
        super().__init__()
        if image_size % 32:
            raise ValueError(f"image_size must be a multiple of 32 (five 2x down blocks), got {image_size}")
        self.image_size, self.latent_dim = image_size, latent_dim
        condition = POSE_DIM + 2 * latent_dim
        self.stem = nn.Conv2d(N_CHANNELS, _ENCODER[0], 3, padding=1)
        self.down = nn.ModuleList(_ResBlock(a, b, True, condition) for a, b in zip(_ENCODER[:-1], _ENCODER[1:]))
        self.rgb_decoder, self.mask_decoder = _Decoder(3, condition), _Decoder(1, condition)

    def forward(
        self, maps: torch.Tensor, pose: torch.Tensor, latent: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        check_shape("maps", maps, (-1, N_CHANNELS, self.image_size, self.image_size))
        check_shape("pose", pose, (maps.shape[0], POSE_DIM))
        if self.latent_dim:
            if latent is None:
                raise ValueError("this CNN is an autoencoder's: it needs a code (B, 2 * latent_dim)")
            check_shape("latent", latent, (maps.shape[0], 2 * self.latent_dim))
            pose = torch.cat([pose, latent.to(pose.dtype)], dim=-1)
        h = self.stem(maps)
        skips = [h]
        for block in self.down:
            h = block(h, pose)
            skips.append(h)
        # logits clamped to +-15 (outputs within 3e-7 of 0 or 1): further out, float32 sigmoid gradients turn
        # denormal, which slowed CPU training 2-6x once the background had been learned
        rgb = torch.sigmoid(self.rgb_decoder(h, skips, pose).clamp(-_LOGIT_BOUND, _LOGIT_BOUND))
        mask = torch.sigmoid((self.mask_decoder(h, skips, pose)[:, 0] - 5).clamp(-_LOGIT_BOUND, _LOGIT_BOUND))
        return rgb, mask
