"""D-NARF: selector-blended canonical coordinates into one NeRF (docs/model.md §4, eqs. E-L)."""

from __future__ import annotations

import torch

from narf.encodings import (
    DIRECTION_WIDTH,
    POINT_WIDTH,
    XI_WIDTH,
    zeta_width,
)
from narf.fields.base import Field, FieldInputs, FieldOutput, masked_softmax
from narf.fields.common import RadianceHead
from narf.fields.selector import PartSelector
from narf.fields.sparse_parts import in_box_pairs, segment_softmax, selector_logits


class DNarf(Field):
    """p = plain softmax of the NARF_D selector over in-box parts; x' = sum p_i (x_i + t_i^can) with
    t_i^can = (J_i - J_0)/s; d' = sum p_i d_i; xi' = sum p_i xi_i. Density from gamma(x'/1.25) (60) and
    gamma(zeta) (152); colour from gamma(d') (24) and gamma(xi'/pi) (48).

    Fast path (``fast``, default): p_i = 0 outside box i, so gamma(u_i) and the selector are evaluated for in-box
    (sample, part) pairs only and the blends are sums over those pairs; the head runs on the samples inside some
    box only (elsewhere sigma = 0, so no render uses their colour; the fast path returns rgb 0 there). The dense
    path (every pair, every sample) is its test reference.
    """

    uses_part_points = True  # the blended canonical point sums x_i

    def __init__(
        self,
        n_parts: int = 19,
        width: int = 256,
        latent_dim: int = 0,
        density_act: str = "leaky_backward",
        fast: bool = True,
        appearance_dim: int = 0,
    ):
        super().__init__(n_parts, latent_dim, appearance_dim)
        self.fast = fast
        self.selector = PartSelector(n_parts)
        self.head = RadianceHead(
            {"x": POINT_WIDTH, "zeta": zeta_width(n_parts)},
            {"dirs": DIRECTION_WIDTH, "pose": XI_WIDTH},
            width,
            latent_dim=latent_dim,
            appearance_dim=appearance_dim,
            density_act=density_act,
        )

    def _forward(self, inputs: FieldInputs) -> FieldOutput:
        _, _, pose, x_local, d_local, u, in_box, z_s, z_a = inputs
        if self.fast:
            return self._forward_in_box(inputs)
        encoded_zeta = self.zeta_encoding(pose)
        probs = masked_softmax(self.selector(self.encode_points(u), encoded_zeta), in_box)  # (R, S, P)
        local = x_local + pose.rest_offsets[:, None]
        canonical = torch.einsum("rsp,rspc->rsc", probs, local)
        blended_dirs = torch.einsum("rsp,rpc->rsc", probs, d_local)
        blended_xi = torch.einsum("rsp,rpc->rsc", probs, pose.pose_features)
        # the selector's gradient through x' passes every frequency; only the pose's is band-limited (docs/model.md §6)
        held = None if self.pose_gradient_freqs is None else torch.einsum("rsp,rspc->rsc", probs, local.detach())
        density = {"x": self.encode_points(canonical / 1.25, None if held is None else held / 1.25)[None]}
        density["zeta"] = encoded_zeta[None]
        colour = {
            "dirs": self.encode_dirs(blended_dirs)[None],
            "pose": self.encode_pose(blended_xi)[None],
        }
        sigma, rgb = self.head(density, colour, z_s, z_a)
        return FieldOutput(sigma[0], rgb[0], probs)

    def _forward_in_box(self, inputs: FieldInputs) -> FieldOutput:
        _, _, pose, x_local, d_local, u, in_box, z_s, z_a = inputs
        r_count, s_count, p_count = in_box.shape
        ray, sample, part = in_box_pairs(in_box)
        flat = ray * s_count + sample
        encoded = self.encode_points(u[ray, sample, part])  # (M, 60)
        chunks = torch.split(encoded, torch.bincount(part, minlength=p_count).tolist())
        logit = selector_logits(self.selector, chunks, ray, part, self.zeta_encoding(pose))
        probs = segment_softmax(logit, flat, r_count * s_count)  # (M,)

        def blend(values: torch.Tensor) -> torch.Tensor:  # sum_i p_i v_i per sample: (M, d) -> (R S, d)
            weighted = probs[:, None] * values  # bfloat16 under autocast (the selector's matmuls)
            return weighted.new_zeros(r_count * s_count, values.shape[-1]).index_add(0, flat, weighted)

        local = x_local[ray, sample, part] + pose.rest_offsets[ray, part]
        canonical = blend(local)
        held = None if self.pose_gradient_freqs is None else blend(local.detach())  # as in _forward
        blended_dirs, blended_xi = blend(d_local[ray, part]), blend(pose.pose_features[ray, part])
        live = in_box.reshape(-1, p_count).any(dim=-1).nonzero()[:, 0]  # samples inside some box
        live_rays = live // s_count
        density = {
            "x": self.encode_points(canonical[live] / 1.25, None if held is None else held[live] / 1.25)[None, None],
            "zeta": self.zeta_encoding(pose)[live_rays, 0][None, None],
        }
        colour = {
            "dirs": self.encode_dirs(blended_dirs[live])[None, None],
            "pose": self.encode_pose(blended_xi[live])[None, None],
        }
        z_s = None if z_s is None else z_s[0, live_rays, 0][None, None]
        z_a = None if z_a is None else z_a[0, live_rays, 0][None, None]
        sigma_live, rgb_live = self.head(density, colour, z_s, z_a)  # (1, 1, L), (1, 1, L, 3)
        sigma = sigma_live.new_zeros(r_count * s_count).index_put((live,), sigma_live[0, 0])
        rgb = rgb_live.new_zeros(r_count * s_count, 3).index_put((live,), rgb_live[0, 0])
        part_probs = probs.new_zeros(r_count * s_count, p_count).index_put((flat, part), probs)
        return FieldOutput(
            sigma.reshape(r_count, s_count), rgb.reshape(r_count, s_count, 3), part_probs.reshape(r_count, s_count, -1)
        )

    def _extra_complete_flops(self) -> int:
        return self.selector.extra_flops()
