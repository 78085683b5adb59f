"""NARF_H: the concatenated per-part inputs masked by the in-box indicator, one shared network (docs/model.md §4)."""

from __future__ import annotations

import torch

from narf.encodings import (
    DIRECTION_WIDTH,
    POINT_FREQS,
    POINT_WIDTH,
    XI_WIDTH,
    zeta_width,
)
from narf.fields.base import Field, FieldInputs, FieldOutput
from narf.fields.common import RadianceHead
from narf.fields.sparse_parts import sparse_density_inputs, sparse_masked_inputs
from narf.grids import GridShape, PartGrids


class NarfH(Field):
    """Density from [b_i gamma(u_i)] (P*60) + gamma(zeta) (152); colour from [b_i gamma(xi_i/pi)] (P*48) and
    [b_i gamma(d_i)] (P*24).

    Args:
        n_parts: P (19).
        width: H (256 paper, smaller on CPU).
        latent_dim: autoencoder latent size per half (0: none).
        appearance_dim: per-frame appearance code size (0: none; ``Field``).
        density_act: ``leaky_backward`` (upstream) or ``softplus``.
        fast: evaluate only in-box (sample, part) pairs (``sparse_parts``); False runs the dense reference.
        grids: None (the paper): each part's density block reads gamma_10(u_i); a GridShape: it reads the part's
            learned multi-resolution grid features g_i(u_i) instead (``narf.grids``, docs/model.md §2, *Part grids*).
        trunk_blocks: the trunk's residual blocks (the paper: 3, 8 layers; ``narf.layers.Trunk``).
        shading: the colour is an albedo under a learned world lighting, its normal turned into the lighting's frame
            by the part rotations blended with the segmentation probabilities (``RadianceHead``; docs/model.md §3).
    """

    def __init__(
        self,
        n_parts: int = 19,
        width: int = 256,
        latent_dim: int = 0,
        density_act: str = "leaky_backward",
        fast: bool = True,
        appearance_dim: int = 0,
        grids: GridShape | None = None,
        trunk_blocks: int = 3,
        shading: bool = False,
    ):
        super().__init__(n_parts, latent_dim, appearance_dim)
        self.fast = fast
        self.grids = None if grids is None else PartGrids(n_parts, grids)
        #: width of one part's block of the density input: gamma_10 (60) or the grid's L F
        self.point_block_width = POINT_WIDTH if grids is None else grids.width
        self.head = RadianceHead(
            {"parts": self.point_block_width * n_parts, "zeta": zeta_width(n_parts)},
            {"pose": XI_WIDTH * n_parts, "dirs": DIRECTION_WIDTH * n_parts},
            width,
            latent_dim=latent_dim,
            appearance_dim=appearance_dim,
            density_act=density_act,
            trunk_blocks=trunk_blocks,
            shading=shading,
        )

    def _density(self, inputs: FieldInputs):
        _, _, pose, _, _, u, in_box, z_s, *_ = inputs
        if not self.fast:  # the dense reference: sigma of the full forward
            return super()._density(inputs)
        encoded_zeta = self.zeta_encoding(pose)
        density = sparse_density_inputs(self, u, in_box, encoded_zeta)
        return self.head.density_embedded(density, {"zeta": encoded_zeta[None]}, z_s)[0]

    def grid_points(self, u: torch.Tensor, part: torch.Tensor | None) -> torch.Tensor:
        """The part grids' features g_i(u) (M, L F) of box coordinates u (M, 3) in parts ``part`` (M,) long; None:
        u holds every part in turn, (R S P, 3) laid out part fastest. The levels open with the coarse-to-fine window
        (``point_window`` over gamma_10's 10 frequencies, mapped onto the L levels; docs/model.md §2), and the pose's
        gradient passes through the round(``pose_gradient_freqs`` L / 10) coarsest levels only, the same map
        (docs/model.md §6)."""
        if part is None:
            part = torch.arange(self.n_parts, device=u.device).repeat(u.shape[0] // self.n_parts)
        levels = self.grids.shape.levels
        alpha = None if self.point_window is None else self.point_window * levels / POINT_FREQS
        freqs = self.pose_gradient_freqs
        gradient_levels = None if freqs is None else max(1, round(freqs * levels / POINT_FREQS))
        return self.grids(u, part, alpha, gradient_levels)

    def part_weights(self, encoded_u, in_box, encoded_zeta):
        """Per-sample part weights used to mask the blocks (R, S, P) and the segmentation probabilities."""
        weights = in_box.to(encoded_u.dtype)
        return weights, weights / weights.sum(-1, keepdim=True).clamp_min(1)

    def _forward(self, inputs: FieldInputs) -> FieldOutput:
        _, _, pose, _, d_local, u, in_box, z_s, z_a = inputs
        if self.fast:
            encoded_zeta = self.zeta_encoding(pose)
            density, colour, probs = sparse_masked_inputs(self, u, in_box, d_local, pose, encoded_zeta)
            rotation = self._normal_rotation(probs, pose)
            sigma, rgb = self.head.forward_embedded(
                density, colour, {"zeta": encoded_zeta[None]}, z_s, z_a, rotation=rotation
            )
            return FieldOutput(sigma[0], rgb[0], probs)
        r, s, p, _ = u.shape
        encoded_u = self.encode_points(u)  # (R, S, P, 60)
        encoded_zeta = self.zeta_encoding(pose)
        weights, probs = self.part_weights(encoded_u, in_box, encoded_zeta)
        block = encoded_u if self.grids is None else self.grid_points(u.reshape(-1, 3), None).reshape(r, s, p, -1)
        masked_u = (weights[..., None] * block).reshape(1, r, s, p * self.point_block_width)
        encoded_xi = self.encode_pose(pose.pose_features)[:, None]  # (R, 1, P, 48)
        encoded_d = self.encode_dirs(d_local)[:, None]  # (R, 1, P, 24)
        colour = {
            "pose": (weights[..., None] * encoded_xi).reshape(1, r, s, p * XI_WIDTH),
            "dirs": (weights[..., None] * encoded_d).reshape(1, r, s, p * DIRECTION_WIDTH),
        }
        density = {"parts": masked_u, "zeta": encoded_zeta[None]}
        sigma, rgb = self.head(density, colour, z_s, z_a, rotation=self._normal_rotation(probs, pose))
        return FieldOutput(sigma[0], rgb[0], probs)

    def _normal_rotation(self, probs: torch.Tensor, pose) -> torch.Tensor | None:
        """With shading, each sample's light_from_normal: L sum_i p_i R_i over the parts' rotations R_i (R, P, 3, 3)
        and the segmentation probabilities p (R, S, P), with L the ray's ``pose.light_from_world`` (the identity when
        None), (1, R, S, 3, 3); None without. Neither the probabilities nor the poses take the shading's gradient (the
        selector answers which part holds a point, as ``part_directions`` keeps the corrected poses to where the body
        is)."""
        if self.head.lighting is None:
            return None
        r, s, p = probs.shape
        rotations = pose.world_from_part[:, :, :3, :3].detach().reshape(r, p, 9).to(probs.dtype)
        world_from_normal = torch.bmm(probs.detach(), rotations).reshape(1, r, s, 3, 3)
        if pose.light_from_world is None:
            return world_from_normal
        return pose.light_from_world.to(probs.dtype)[None, :, None] @ world_from_normal
