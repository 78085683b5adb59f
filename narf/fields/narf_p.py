"""NARF_P: one network per part, combined by a softmax over in-box part densities (docs/model.md §4, Eq. 15)."""

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
from narf.fields.sparse_parts import in_box_pairs

#: the fast path packs when at most this share of the (sample, part) pairs are in box (else the dense pass)
PACKED_SHARE = 0.5


class NarfP(Field):
    """Per part i: density from gamma(u_i) (60) + gamma(zeta) (152), colour from gamma(xi_i/pi) (48), gamma(d_i)
    (24); sigma_i = 0 out of box; p_i = softmax_i(sigma_i / tau) over in-box parts; sigma = sum p_i sigma_i,
    c = sum p_i c_i. Segmentation uses the density softmax at tau = 0.01.

    Fast path (``fast``, default): a part's network only matters where its box holds the sample (sigma_i = 0 and
    p_i = 0 elsewhere), so each part's network runs only on its in-box samples, packed in equal blocks (each within
    one part) into one batched pass; the dense path (every network on every sample) is its test reference.

    Args:
        n_parts: P. width: H per part (paper 32/64/128/256). temperature: tau (10). fast: in-box evaluation only.
    """

    def __init__(
        self,
        n_parts: int = 19,
        width: int = 256,
        latent_dim: int = 0,
        density_act: str = "leaky_backward",
        temperature: float = 10.0,
        fast: bool = True,
        appearance_dim: int = 0,
    ):
        super().__init__(n_parts, latent_dim, appearance_dim)
        self.fast = fast
        if temperature <= 0:
            raise ValueError(f"temperature must be positive, got {temperature}")
        self.temperature = temperature
        self.head = RadianceHead(
            {"u": POINT_WIDTH, "zeta": zeta_width(n_parts)},
            {"pose": XI_WIDTH, "dirs": DIRECTION_WIDTH},
            width,
            groups=n_parts,
            latent_dim=latent_dim,
            appearance_dim=appearance_dim,
            density_act=density_act,
        )

    def _forward(self, inputs: FieldInputs) -> FieldOutput:
        _, _, pose, _, d_local, u, in_box, z_s, z_a = inputs
        # the packed pass costs at most 1.5 x the in-box pairs (see _in_box_heads): where most pairs are in box it
        # saves little over the dense pass and only adds the packing
        if self.fast and in_box.sum() <= PACKED_SHARE * in_box.numel():
            sigma_parts, rgb_parts = self._in_box_heads(pose, d_local, u, in_box, z_s, z_a)
        else:
            sigma_parts, rgb_parts = self._all_heads(pose, d_local, u, z_s, z_a)
        sigma_parts = torch.where(in_box, sigma_parts, torch.zeros_like(sigma_parts))
        probs = masked_softmax(sigma_parts / self.temperature, in_box)
        sigma = (probs * sigma_parts).sum(-1)
        rgb = torch.einsum("rsp,rspc->rsc", probs, rgb_parts)
        segmentation = masked_softmax(sigma_parts.detach() / 0.01, in_box)
        return FieldOutput(sigma, rgb, segmentation)

    def _all_heads(self, pose, d_local, u, z_s, z_a) -> tuple[torch.Tensor, torch.Tensor]:
        """Every part's network on every sample (the reference): sigma_i (R, S, P), c_i (R, S, P, 3)."""
        p = self.n_parts
        density = {
            "u": self.encode_points(u).permute(2, 0, 1, 3),
            "zeta": self.zeta_encoding(pose)[None].expand(p, -1, -1, -1),
        }
        colour = {
            "pose": self.encode_pose(pose.pose_features).permute(1, 0, 2)[:, :, None],
            "dirs": self.encode_dirs(d_local).permute(1, 0, 2)[:, :, None],
        }
        sigma_parts, rgb_parts = self.head(density, colour, z_s, z_a)  # (P, R, S), (P, R, S, 3)
        return sigma_parts.permute(1, 2, 0), rgb_parts.permute(1, 2, 0, 3)

    def _in_box_heads(self, pose, d_local, u, in_box, z_s, z_a) -> tuple[torch.Tensor, torch.Tensor]:
        """Part i's network on the samples inside box i only, zeros elsewhere: (R, S, P), (R, S, P, 3).

        The M in-box pairs, sorted by part, are cut into blocks of b = ceil(M / 2P) pairs, each block within one
        part (its last block zero-padded); block j goes through part ``group_index[j]``'s network. One batched
        pass then costs at most M + P b <= 1.5 M pair evaluations, however unevenly the parts share the samples.
        """
        r_count, s_count, p_count = in_box.shape
        ray, sample, part = in_box_pairs(in_box)
        counts = torch.bincount(part, minlength=p_count)
        block = max(-(-part.numel() // (2 * p_count)), 1)
        blocks_of_part = (counts + block - 1) // block
        group_index = torch.repeat_interleave(torch.arange(p_count, device=part.device), blocks_of_part)
        slot = torch.arange(part.numel(), device=part.device) - (torch.cumsum(counts, 0) - counts)[part]
        first_block = torch.cumsum(blocks_of_part, 0) - blocks_of_part
        block_id = first_block[part] + slot // block
        position = slot % block

        def packed(values: torch.Tensor) -> torch.Tensor:  # (M, d) -> (blocks, 1, b, d), zero padding
            out = values.new_zeros(group_index.numel(), block, values.shape[-1])
            return out.index_put((block_id, position), values)[:, None]

        density = {
            "u": packed(self.encode_points(u[ray, sample, part])),
            "zeta": packed(self.zeta_encoding(pose)[ray, 0]),
        }
        colour = {
            "pose": packed(self.encode_pose(pose.pose_features[ray, part])),
            "dirs": packed(self.encode_dirs(d_local[ray, part])),
        }
        z_s = None if z_s is None else packed(z_s[0, ray, 0])
        z_a = None if z_a is None else packed(z_a[0, ray, 0])
        sigma_packed, rgb_packed = self.head(density, colour, z_s, z_a, group_index)  # (blocks, 1, b), (.., 3)
        # zeros of the outputs' dtype: under autocast the head returns bfloat16
        sigma_parts = sigma_packed.new_zeros(r_count, s_count, p_count)
        sigma_parts = sigma_parts.index_put((ray, sample, part), sigma_packed[block_id, 0, position])
        rgb_parts = rgb_packed.new_zeros(r_count, s_count, p_count, 3)
        rgb_parts = rgb_parts.index_put((ray, sample, part), rgb_packed[block_id, 0, position])
        return sigma_parts, rgb_parts
