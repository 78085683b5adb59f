"""The part selector of NARF_D and D-NARF (docs/model.md §4, Eqs. 21-23)."""

from __future__ import annotations

import torch
from torch import nn

from narf.encodings import POINT_WIDTH, zeta_width
from narf.layers import EqualLinear


class PartSelector(nn.Module):
    """a_i = ReLU(W_i gamma(u_i) + V_i gamma(zeta) + b_i) in R^hidden; o_i = w_i^T a_i + b'_i.

    W_i: per part 60 -> hidden (grouped); V: dense 152 -> P * hidden; w_i: per part hidden -> 1.

    Args:
        n_parts: P.
        u_dim: width of gamma(u_i) (60).
        zeta_dim: width of gamma(zeta) (None: ``zeta_width(n_parts)``, 152 for 19 parts; 0: no zeta term).
        hidden: selector width per part (10).
    """

    def __init__(self, n_parts: int, u_dim: int = POINT_WIDTH, zeta_dim: int | None = None, hidden: int = 10):
        super().__init__()
        zeta_dim = zeta_width(n_parts) if zeta_dim is None else zeta_dim
        self.n_parts, self.hidden = n_parts, hidden
        self.local = EqualLinear(u_dim, hidden, groups=n_parts)
        self.bones = EqualLinear(zeta_dim, n_parts * hidden, bias=False) if zeta_dim else None
        self.out = EqualLinear(hidden, 1, groups=n_parts)

    def forward(self, encoded_u: torch.Tensor, encoded_zeta: torch.Tensor | None) -> torch.Tensor:
        """encoded_u (R, S, P, 60), encoded_zeta (R, 1, 152) -> logits o (R, S, P)."""
        r, s, p, d = encoded_u.shape
        local = self.local(encoded_u.permute(2, 0, 1, 3).reshape(p, r * s, d)).reshape(p, r, s, self.hidden)
        if self.bones is not None and encoded_zeta is not None:
            bones = self.bones(encoded_zeta.reshape(1, r, -1)).reshape(r, 1, p, self.hidden).permute(2, 0, 1, 3)
            local = local + bones
        hidden = torch.relu(local)
        return self.out(hidden.reshape(p, r * s, self.hidden)).reshape(p, r, s).permute(1, 2, 0)

    def extra_flops(self) -> int:
        return self.n_parts * self.hidden  # the ReLU
