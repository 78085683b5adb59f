"""NARF_D: selector-masked concatenation (docs/model.md §4, Eqs. 21-23), and its sigmoid ablation (eq. A)."""

from __future__ import annotations

import torch

from narf.fields.base import masked_softmax, rescale_selection
from narf.fields.narf_h import NarfH
from narf.fields.selector import PartSelector
from narf.grids import GridShape


class NarfD(NarfH):
    """NARF_H's network with a learned part selector: p = softmax over in-box parts of o_i (or sigmoid),
    rescaled p <- p sqrt(N)/|p|; the blocks are masked by p. Segmentation uses the un-rescaled p.

    Args:
        selector: ``softmax`` (default) or ``sigmoid`` (ablation).
        encoding: ``frequency`` (the paper: the density reads gamma_10(u_i)) or ``grid`` (learned part grids of
            ``grid_levels`` levels of ``grid_features`` features, ``grid_min_resolution`` to ``grid_max_resolution``
            cells per axis, 2^``grid_log2_rows`` rows a level and part; ``narf.grids``). The selector reads
            gamma_10(u_i) either way.
        trunk_blocks: the trunk's residual blocks (the paper: 3; fewer: the small network on the grids).
        shading: albedo under a learned world lighting (``NarfH``; docs/model.md §3, *Shading*; not in the paper).
        (others as NarfH)
    """

    def __init__(
        self,
        n_parts: int = 19,
        width: int = 256,
        latent_dim: int = 0,
        density_act: str = "leaky_backward",
        selector: str = "softmax",
        fast: bool = True,
        appearance_dim: int = 0,
        encoding: str = "frequency",
        grid_levels: int = 8,
        grid_features: int = 2,
        grid_min_resolution: int = 8,
        grid_max_resolution: int = 128,
        grid_log2_rows: int = 12,
        trunk_blocks: int = 3,
        shading: bool = False,
    ):
        if encoding not in ("frequency", "grid"):
            raise ValueError(f"encoding must be 'frequency' or 'grid', got '{encoding}'")
        grids = None
        if encoding == "grid":
            grids = GridShape(grid_levels, grid_features, grid_min_resolution, grid_max_resolution, grid_log2_rows)
        super().__init__(n_parts, width, latent_dim, density_act, fast, appearance_dim, grids, trunk_blocks, shading)
        if selector not in ("softmax", "sigmoid"):
            raise ValueError(f"selector must be 'softmax' or 'sigmoid', got '{selector}'")
        self.selector_kind = selector
        self.selector = PartSelector(n_parts)

    def part_weights(self, encoded_u, in_box, encoded_zeta):
        logits = self.selector(encoded_u, encoded_zeta)
        if self.selector_kind == "softmax":
            probs = masked_softmax(logits, in_box)
        else:
            probs = torch.where(in_box, torch.sigmoid(logits), torch.zeros_like(logits))
        return rescale_selection(probs), probs

    def _extra_complete_flops(self) -> int:
        return self.selector.extra_flops()
