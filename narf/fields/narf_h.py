"""NARF_H: the concatenated per-part inputs masked by the in-box indicator, one shared network (docs/model.md §4)."""

from __future__ import annotations

from narf.encodings import (
    DIRECTION_WIDTH,
    POINT_WIDTH,
    XI_WIDTH,
    zeta_width,
)
from narf.fields.base import Field, FieldInputs, FieldOutput
from narf.fields.common import RadianceHead
from narf.fields.sparse_parts import sparse_density_inputs, sparse_masked_inputs


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
    """

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
        self.head = RadianceHead(
            {"parts": POINT_WIDTH * n_parts, "zeta": zeta_width(n_parts)},
            {"pose": XI_WIDTH * n_parts, "dirs": DIRECTION_WIDTH * n_parts},
            width,
            latent_dim=latent_dim,
            appearance_dim=appearance_dim,
            density_act=density_act,
        )

    def _density(self, inputs: FieldInputs):
        _, _, pose, _, _, u, in_box, z_s, *_ = inputs
        if not self.fast:  # the dense reference: sigma of the full forward
            return super()._density(inputs)
        encoded_zeta = self.zeta_encoding(pose)
        density = sparse_density_inputs(self, u, in_box, encoded_zeta)
        return self.head.density_embedded(density, {"zeta": encoded_zeta[None]}, z_s)[0]

    def part_weights(self, encoded_u, in_box, encoded_zeta):
        """Per-sample part weights used to mask the blocks (R, S, P) and the segmentation probabilities."""
        weights = in_box.to(encoded_u.dtype)
        return weights, weights / weights.sum(-1, keepdim=True).clamp_min(1)

    def _forward(self, inputs: FieldInputs) -> FieldOutput:
        _, _, pose, _, d_local, u, in_box, z_s, z_a = inputs
        if self.fast:
            encoded_zeta = self.zeta_encoding(pose)
            density, colour, probs = sparse_masked_inputs(self, u, in_box, d_local, pose, encoded_zeta)
            sigma, rgb = self.head.forward_embedded(density, colour, {"zeta": encoded_zeta[None]}, z_s, z_a)
            return FieldOutput(sigma[0], rgb[0], probs)
        r, s, p, _ = u.shape
        encoded_u = self.encode_points(u)  # (R, S, P, 60)
        encoded_zeta = self.zeta_encoding(pose)
        weights, probs = self.part_weights(encoded_u, in_box, encoded_zeta)
        masked_u = (weights[..., None] * encoded_u).reshape(1, r, s, p * POINT_WIDTH)
        encoded_xi = self.encode_pose(pose.pose_features)[:, None]  # (R, 1, P, 48)
        encoded_d = self.encode_dirs(d_local)[:, None]  # (R, 1, P, 24)
        colour = {
            "pose": (weights[..., None] * encoded_xi).reshape(1, r, s, p * XI_WIDTH),
            "dirs": (weights[..., None] * encoded_d).reshape(1, r, s, p * DIRECTION_WIDTH),
        }
        sigma, rgb = self.head({"parts": masked_u, "zeta": encoded_zeta[None]}, colour, z_s, z_a)
        return FieldOutput(sigma[0], rgb[0], probs)
