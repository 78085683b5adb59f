"""D-NARF: selector-blended canonical coordinates into one NeRF (docs/model.md §4, eqs. E-L)."""

from __future__ import annotations

import math

import torch

from narf.encodings import positional_encoding
from narf.fields.base import Field, FieldOutput, masked_softmax
from narf.fields.common import RadianceHead
from narf.fields.selector import PartSelector


class DNarf(Field):
    """p = plain softmax of the NARF_D selector over in-box parts; x' = sum p_i (x_i + t_i^can) with
    t_i^can = (J_i - J_0)/s; d' = sum p_i d_i; xi' = sum p_i xi_i. Density from gamma(x'/1.25) (60) and
    gamma(zeta) (152); colour from gamma(d') (24) and gamma(xi'/pi) (48)."""

    def __init__(self, n_parts: int = 19, width: int = 256, latent_dim: int = 0, density_act: str = "leaky_backward"):
        super().__init__(n_parts, latent_dim)
        self.selector = PartSelector(n_parts)
        self.head = RadianceHead(
            {"x": 60, "zeta": 152}, {"dirs": 24, "pose": 48}, width, latent_dim=latent_dim, density_act=density_act
        )

    def _forward(self, points, dirs, pose, x_local, d_local, u, in_box, z_s, z_a) -> FieldOutput:
        encoded_zeta = self.zeta_encoding(pose)
        probs = masked_softmax(self.selector(positional_encoding(u, 10), encoded_zeta), in_box)  # (R, S, P)
        canonical = torch.einsum("rsp,rspc->rsc", probs, x_local + pose.rest_offsets[:, None])
        blended_dirs = torch.einsum("rsp,rpc->rsc", probs, d_local)
        blended_xi = torch.einsum("rsp,rpc->rsc", probs, pose.pose_features)
        density = {"x": positional_encoding(canonical / 1.25, 10)[None], "zeta": encoded_zeta[None]}
        colour = {
            "dirs": positional_encoding(blended_dirs, 4)[None],
            "pose": positional_encoding(blended_xi / math.pi, 4)[None],
        }
        sigma, rgb = self.head(density, colour, z_s, z_a)
        return FieldOutput(sigma[0], rgb[0], probs)

    def _extra_complete_flops(self) -> int:
        return self.selector.extra_flops()
