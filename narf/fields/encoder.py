"""Image encoder of the autoencoder (docs/model.md §4): 128^2 RGB -> z (512) = [z_s (256), z_a (256)]."""

from __future__ import annotations

import torch
from torch import nn

from narf.geometry import check_shape


class _PreActDown(nn.Module):
    """Pre-activation residual block that halves the resolution: BN-ReLU-conv3-BN-ReLU-conv3 + 1x1 skip, avgpool."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.body = nn.Sequential(
            nn.BatchNorm2d(c_in),
            nn.ReLU(),
            nn.Conv2d(c_in, c_out, 3, padding=1),
            nn.BatchNorm2d(c_out),
            nn.ReLU(),
            nn.Conv2d(c_out, c_out, 3, padding=1),
        )
        self.skip = nn.Conv2d(c_in, c_out, 1) if c_in != c_out else nn.Identity()
        self.pool = nn.AvgPool2d(2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.pool(self.body(x) + self.skip(x))


class ImageEncoder(nn.Module):
    """3x3 conv 3->c, five residual down blocks (c->2c->4c->8c->16c->16c at 64..4 px), ReLU, flatten, linear ->
    2 * latent_dim, with c = ``base_channels`` (paper: 32, i.e. 32->...->512 and an 8192-wide flatten; a smaller c
    is the CPU default). Deterministic (no KL, no GAN)."""

    def __init__(self, latent_dim: int = 256, image_size: int = 128, base_channels: int = 32):
        super().__init__()
        if image_size % 32:
            raise ValueError(f"image_size must be a multiple of 32, got {image_size}")
        self.image_size = image_size
        if base_channels < 1:
            raise ValueError(f"base_channels must be positive, got {base_channels}")
        channels = tuple(base_channels * k for k in (1, 2, 4, 8, 16, 16))
        self.stem = nn.Conv2d(3, channels[0], 3, padding=1)
        self.blocks = nn.Sequential(*(_PreActDown(a, b) for a, b in zip(channels[:-1], channels[1:])))
        self.head = nn.Linear(channels[-1] * (image_size // 32) ** 2, 2 * latent_dim)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """images (B, 3, S, S) in [0, 1] -> z (B, 2 * latent_dim)."""
        check_shape("images", images, (-1, 3, self.image_size, self.image_size))
        features = torch.relu(self.blocks(self.stem(images)))
        return self.head(features.flatten(1))
