"""NARF_D: selector-masked concatenation (docs/model.md §4, Eqs. 21-23), and its sigmoid ablation (eq. A)."""

from __future__ import annotations

import torch

from narf.fields.base import masked_softmax, rescale_selection
from narf.fields.narf_h import NarfH
from narf.fields.selector import PartSelector


class NarfD(NarfH):
    """NARF_H's network with a learned part selector: p = softmax over in-box parts of o_i (or sigmoid),
    rescaled p <- p sqrt(N)/|p|; the blocks are masked by p. Segmentation uses the un-rescaled p.

    Args:
        selector: ``softmax`` (default) or ``sigmoid`` (ablation).
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
    ):
        super().__init__(n_parts, width, latent_dim, density_act, fast, appearance_dim)
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
