"""NARF_P: one network per part, combined by a softmax over in-box part densities (docs/model.md §4, Eq. 15)."""

from __future__ import annotations

import math

import torch

from narf.encodings import positional_encoding
from narf.fields.base import Field, FieldOutput, masked_softmax
from narf.fields.common import RadianceHead


class NarfP(Field):
    """Per part i: density from gamma(u_i) (60) + gamma(zeta) (152), colour from gamma(xi_i/pi) (48), gamma(d_i)
    (24); sigma_i = 0 out of box; p_i = softmax_i(sigma_i / tau) over in-box parts; sigma = sum p_i sigma_i,
    c = sum p_i c_i. Segmentation uses the density softmax at tau = 0.01.

    Args:
        n_parts: P. width: H per part (paper 32/64/128/256). temperature: tau (10).
    """

    def __init__(
        self,
        n_parts: int = 19,
        width: int = 256,
        latent_dim: int = 0,
        density_act: str = "leaky_backward",
        temperature: float = 10.0,
    ):
        super().__init__(n_parts, latent_dim)
        if temperature <= 0:
            raise ValueError(f"temperature must be positive, got {temperature}")
        self.temperature = temperature
        self.head = RadianceHead(
            {"u": 60, "zeta": 152},
            {"pose": 48, "dirs": 24},
            width,
            groups=n_parts,
            latent_dim=latent_dim,
            density_act=density_act,
        )

    def _forward(self, points, dirs, pose, x_local, d_local, u, in_box, z_s, z_a) -> FieldOutput:
        p = self.n_parts
        density = {
            "u": positional_encoding(u, 10).permute(2, 0, 1, 3),
            "zeta": self.zeta_encoding(pose)[None].expand(p, -1, -1, -1),
        }
        colour = {
            "pose": positional_encoding(pose.pose_features / math.pi, 4).permute(1, 0, 2)[:, :, None],
            "dirs": positional_encoding(d_local, 4).permute(1, 0, 2)[:, :, None],
        }
        sigma_parts, rgb_parts = self.head(density, colour, z_s, z_a)  # (P, R, S), (P, R, S, 3)
        sigma_parts = sigma_parts.permute(1, 2, 0)
        sigma_parts = torch.where(in_box, sigma_parts, torch.zeros_like(sigma_parts))
        probs = masked_softmax(sigma_parts / self.temperature, in_box)
        sigma = (probs * sigma_parts).sum(-1)
        rgb = torch.einsum("rsp,prsc->rsc", probs, rgb_parts)
        segmentation = masked_softmax(sigma_parts.detach() / 0.01, in_box)
        return FieldOutput(sigma, rgb, segmentation)
