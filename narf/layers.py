"""Layers shared by the NARF fields (docs/model.md §3).

Every linear layer is *grouped*: ``groups`` independent layers applied to inputs shaped (G, N, in), so that
NARF_P's 19 per-part networks and the per-part selector run as one batched matmul. Each layer reports its cost
under the upstream accounting rules (docs/model.md §8).
"""

from __future__ import annotations

import math

import torch
from torch import nn


class GroupedLinear(nn.Module):
    """``groups`` linear layers: (G, N, in) -> (G, N, out). Base of the two parametrisations below.

    Args:
        in_features / out_features: per group.
        groups: number of independent layers.
        paper_skip: excluded from the paper-comparable FLOP/memory count (upstream skips the colour H->H/2).
    """

    def __init__(
        self, in_features: int, out_features: int, groups: int = 1, bias: bool = True, paper_skip: bool = False
    ):
        super().__init__()
        self.in_features, self.out_features = in_features, out_features
        self.groups, self.paper_skip = groups, paper_skip
        self.weight = nn.Parameter(torch.randn(groups, out_features, in_features))
        self.bias = nn.Parameter(torch.zeros(groups, 1, out_features)) if bias else None

    def effective_weight(self) -> torch.Tensor:
        raise NotImplementedError

    def forward(self, inputs: torch.Tensor, group_index: torch.Tensor | None = None) -> torch.Tensor:
        """(G, N, in) -> (G, N, out); with ``group_index`` (G',) long, inputs (G', N, in) go through the layers
        ``group_index`` (several blocks may share one layer: ragged groups packed in equal blocks)."""
        weight, bias = self.effective_weight().transpose(1, 2), self.bias
        if group_index is not None:
            weight = weight.index_select(0, group_index)
            bias = None if bias is None else bias.index_select(0, group_index)
        if bias is None:
            return torch.bmm(inputs, weight)
        return torch.baddbmm(bias, inputs, weight)

    def flops(self) -> int:
        """2 * in * out / groups with in, out the totals over groups."""
        return 2 * self.groups * self.in_features * self.out_features

    def outputs(self) -> int:
        return self.groups * self.out_features


class WNLinear(GroupedLinear):
    """Weight-normalised: each unit's weight vector has unit norm at run time (N(0, 1) init)."""

    def effective_weight(self) -> torch.Tensor:
        return self.weight / self.weight.norm(dim=2, keepdim=True).clamp_min(1e-12)


class EqualLinear(GroupedLinear):
    """Equalised learning rate: N(0, 1) weights times 1/sqrt(fan_in) at run time."""

    def effective_weight(self) -> torch.Tensor:
        return self.weight / math.sqrt(self.in_features)


class _LeakyBackwardReLU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, inputs):
        ctx.save_for_backward(inputs)
        return inputs.clamp_min(0)

    @staticmethod
    def backward(ctx, grad):
        (inputs,) = ctx.saved_tensors
        negative_push = (inputs < 0) & (grad < 0)  # lets negative pre-activations rise, never fall further
        return torch.where(inputs >= 0, grad, torch.where(negative_push, 0.1 * grad, torch.zeros_like(grad)))


def leaky_backward_relu(inputs: torch.Tensor) -> torch.Tensor:
    """Forward max(0, a); backward g for a >= 0, 0.1 g for a < 0 when g < 0, else 0 (upstream density act)."""
    return _LeakyBackwardReLU.apply(inputs)


class _ScaledUnitRows(torch.autograd.Function):
    @staticmethod
    def forward(ctx, inputs, scale: float, eps: float):
        norm = inputs.norm(dim=-1, keepdim=True)
        inverse = norm.clamp_min(eps).reciprocal()
        ctx.save_for_backward(inputs, inverse, norm > eps)
        ctx.scale = scale
        return inputs * (inverse * scale)

    @staticmethod
    def backward(ctx, grad):
        inputs, inverse, live = ctx.saved_tensors
        # d(s x/|x|) = s/|x| (g - x (x.g)/|x|^2); where the clamp holds |x| at eps: s g/eps
        coefficient = torch.where(live, (grad * inputs).sum(-1, keepdim=True) * inverse * inverse, 0.0)
        return torch.addcmul(grad, inputs, coefficient, value=-1).mul_(inverse * ctx.scale), None, None


def scaled_unit_rows(inputs: torch.Tensor, scale: float, eps: float = 1e-6) -> torch.Tensor:
    """s x / max(|x|, eps) over the last dim, (..., H) -> (..., H), with a hand-written backward (four passes over
    the rows instead of autograd's division, norm and accumulation; the autograd form is the test oracle)."""
    return _ScaledUnitRows.apply(inputs, scale, eps)


def density_activation(name: str):
    if name == "leaky_backward":
        return leaky_backward_relu
    if name == "softplus":
        return nn.functional.softplus
    raise ValueError(f"density activation must be 'leaky_backward' or 'softplus', got '{name}'")


class Trunk(nn.Module):
    """2 + 2 B linear layers of width H: Linear+ReLU, B residual blocks h + ReLU(Lin(ReLU(Lin(h)))), Linear+ReLU.
    The paper's trunk has B = 3 (8 layers); fewer blocks make the small network on top of the part grids
    (docs/model.md §2, *Part grids*)."""

    def __init__(self, width: int, groups: int = 1, blocks: int = 3):
        super().__init__()
        if blocks < 0:
            raise ValueError(f"trunk blocks must be >= 0, got {blocks}")
        self.width, self.groups = width, groups
        self.first = WNLinear(width, width, groups)
        self.blocks = nn.ModuleList(
            nn.ModuleList([WNLinear(width, width, groups), WNLinear(width, width, groups)]) for _ in range(blocks)
        )
        self.last = WNLinear(width, width, groups)

    def forward(self, hidden: torch.Tensor, group_index: torch.Tensor | None = None) -> torch.Tensor:
        """(G, N, H) -> (G, N, H); ``group_index`` as in :meth:`GroupedLinear.forward`."""
        # in-place ReLUs on fresh matmul outputs (their backward needs the inputs only): no extra (N, H) buffers
        hidden = torch.relu_(self.first(hidden, group_index))
        for lin_a, lin_b in self.blocks:
            hidden = hidden + torch.relu_(lin_b(torch.relu_(lin_a(hidden, group_index)), group_index))
        return torch.relu_(self.last(hidden, group_index))

    def extra_flops(self) -> int:
        """+H per ReLU module (2 + 2 B) and per residual add (B)."""
        return self.groups * self.width * (2 + 3 * len(self.blocks))

    def extra_memory(self) -> int:
        """+H per residual block."""
        return self.groups * self.width * len(self.blocks)
