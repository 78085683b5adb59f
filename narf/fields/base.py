"""Base class of the NeRF-type fields: part boxes (and the body's shells within them), box coordinates, outputs and
cost accounting."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import nn

from narf.encodings import POINT_FREQS, POSE_FREQS, point_encoding, positional_encoding, windowed
from narf.fields.common import PoseBatch, RadianceHead, part_box_coordinates, part_directions, part_local
from narf.geometry import check_shape
from narf.layers import GroupedLinear
from narf.occupancy import flat_cell_index


@dataclass
class FieldOutput:
    """sigma (R, S) >= 0; rgb (R, S, 3) in [0, 1] (with shading >= 0: an albedo in [0, 1] times the irradiance,
    docs/model.md §3); part_probs (R, S, P) for segmentation, or None."""

    sigma: torch.Tensor
    rgb: torch.Tensor
    part_probs: torch.Tensor | None = None


class FieldInputs(NamedTuple):
    """What ``Field._forward`` / ``_density`` take, in order: the validated arguments of ``Field.forward``, x_local
    (R, S, P, 3) or None, d_local (R, P, 3), u (R, S, P, 3), in_box (R, S, P) and the latent halves (1, R, 1, L) or
    None."""

    points: torch.Tensor
    dirs: torch.Tensor
    pose: PoseBatch
    x_local: torch.Tensor | None
    d_local: torch.Tensor
    u: torch.Tensor
    in_box: torch.Tensor
    z_s: torch.Tensor | None
    z_a: torch.Tensor | None


@dataclass(frozen=True)
class Cost:
    """Costs under the upstream rules (docs/model.md §8): parameters, per-ray FLOPs and activation memory."""

    params: int
    flops_per_ray: int
    memory_per_ray: int
    flops_per_ray_complete: int


SAMPLES_FOR_COST = 96


class Field(nn.Module):
    """A NeRF-type field over P parts with fixed boxes (centres, half-extents in body units).

    Subclasses implement ``_forward(inputs: FieldInputs)`` (and may implement ``_density`` alike); ``inputs.x_local``
    is None unless the subclass sets ``uses_part_points``. Encoded widths come from ``narf.encodings`` and
    ``n_parts``. Every field's constructor also takes ``latent_dim`` (the autoencoder's z_s, z_a) and
    ``appearance_dim`` (a per-frame appearance code in z_a's place, read from ``PoseBatch.appearance``; docs/model.md
    §4, *Per-frame appearance*).
    """

    #: whether ``_forward`` reads x_local (R, S, P, 3); the others get None and skip computing it
    uses_part_points = False
    #: the point encodings' frequencies through which gradient reaches the part-local points, and so the pose
    #: (``narf.encodings.point_encoding``; part grids: their round(freqs L / 10) coarsest levels); None: all. Set
    #: while poses are corrected; no effect on the field's own gradients or on any value.
    pose_gradient_freqs: int | None = None
    #: what the colour may depend on (docs/model.md §4, *Colour conditioning*), set from the model config by
    #: ``fitting.trainer.configure_field``: the direction encoding's kept frequencies (0: no view direction), the
    #: view direction's jitter in training (radians, per tangent axis) and the probability that a training ray's
    #: pose features xi are zeroed; and the frequencies of xi's encoding that the colour reads (``encode_pose``)
    view_freqs: int = POSE_FREQS
    view_jitter: float = 0.0
    pose_dropout: float = 0.0
    pose_freqs: int = POSE_FREQS
    #: whether the density reads the pose features xi (P-NeRF, RP-NeRF): their dropout would reach the geometry
    pose_in_density = False
    #: coarse-to-fine window of the point encoding gamma_10 (``narf.encodings.frequency_window``); None: all open
    point_window: float | None = None

    def __init__(self, n_parts: int, latent_dim: int = 0, appearance_dim: int = 0):
        super().__init__()
        self.n_parts, self.latent_dim, self.appearance_dim = n_parts, latent_dim, appearance_dim
        self.register_buffer("box_centres", torch.zeros(n_parts, 3))
        self.register_buffer("box_half_extents", torch.ones(n_parts, 3))
        #: (P, N, N, N) bool over each box's coordinates: where the part may hold density (docs/model.md §1, *Body
        #: shells*); one cell that is True (the default) is the whole box, the paper's model
        self.register_buffer("part_shells", torch.ones(n_parts, 1, 1, 1, dtype=torch.bool))
        #: optional narf.occupancy.OccupancyGrid; renderers narrow their ray bounds with it (docs/model.md §5)
        self.occupancy: nn.Module | None = None

    def set_boxes(self, centres: torch.Tensor, half_extents: torch.Tensor) -> None:
        check_shape("centres", centres, (self.n_parts, 3))
        check_shape("half_extents", half_extents, (self.n_parts, 3))
        if (half_extents <= 0).any():
            raise ValueError("box half-extents must be positive")
        self.box_centres.copy_(centres)
        self.box_half_extents.copy_(half_extents)

    def set_shells(self, shells: torch.Tensor) -> None:
        """Limit each part to the cells of its box that ``shells`` (P, N, N, N) bool marks (docs/model.md §1)."""
        check_shape("shells", shells, (self.n_parts, -1, -1, -1))
        n = shells.shape[1]
        if shells.shape[1:] != (n, n, n) or shells.dtype != torch.bool:
            raise ValueError(f"shells: expected (P, N, N, N) bool, got {tuple(shells.shape)} {shells.dtype}")
        self.part_shells = shells.to(self.box_centres.device)

    def in_parts(self, u: torch.Tensor) -> torch.Tensor:
        """Which part holds each point: box coordinates u (..., P, 3) -> (..., P) bool, ``max|u_i| <= 1`` and, with
        shells set, the point's cell of part i's shell."""
        in_box = u.abs().amax(dim=-1) <= 1
        n = self.part_shells.shape[1]
        if n == 1:
            return in_box
        part = torch.arange(self.n_parts, device=u.device)
        return in_box & self.part_shells.reshape(-1)[flat_cell_index(u, part, n, self.n_parts)]

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # the shells' resolution is the saved one; a checkpoint written before shells existed holds none: whole boxes
        key = prefix + "part_shells"
        if key not in state_dict:
            state_dict[key] = torch.ones(self.n_parts, 1, 1, 1, dtype=torch.bool)
        self.part_shells = torch.empty_like(state_dict[key], device=self.part_shells.device)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def box_coordinates(self, x_local: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """u_i = (x_i - c_i) / h_i and :meth:`in_parts` of it: (R, S, P, 3), (R, S, P)."""
        u = (x_local - self.box_centres) / self.box_half_extents
        return u, self.in_parts(u)

    def encode_points(self, values: torch.Tensor, without_pose: torch.Tensor | None = None) -> torch.Tensor:
        """gamma_10 of part-local points or box coordinates (..., 3) -> (..., 60), through the coarse-to-fine
        window and with the pose's gradient band-limited (``narf.encodings.point_encoding``, which says what
        ``without_pose`` is)."""
        encoded = point_encoding(values, self.pose_gradient_freqs, without_pose)
        return windowed(encoded, self.point_window, POINT_FREQS)

    def encode_dirs(self, dirs: torch.Tensor) -> torch.Tensor:
        """gamma_4 of view directions (..., 3) -> (..., 24), the frequencies k >= ``view_freqs`` zeroed (all of them
        at 0: the colour does not see the view direction)."""
        return windowed(positional_encoding(dirs, POSE_FREQS), float(self.view_freqs), POSE_FREQS)

    def encode_pose(self, pose_features: torch.Tensor) -> torch.Tensor:
        """gamma_4(xi/pi) of pose features (..., 6) -> (..., 48) for the colour, the frequencies k >= ``pose_freqs``
        taken at xi = 0 (sin 0, cos 1): at 0 every pose encodes as gamma(0), so the colour does not depend on the pose
        (docs/model.md §4, *Colour conditioning*)."""
        encoded = positional_encoding(pose_features / math.pi, POSE_FREQS)
        if self.pose_freqs >= POSE_FREQS:
            return encoded
        still = positional_encoding(torch.zeros_like(pose_features), POSE_FREQS)
        return still + windowed(encoded - still, float(self.pose_freqs), POSE_FREQS)

    @staticmethod
    def zeta_encoding(pose: PoseBatch) -> torch.Tensor:
        """gamma_4(zeta) per ray: (R, 1, 152)."""
        return positional_encoding(pose.bone_lengths, POSE_FREQS)[:, None]

    def forward(
        self, points: torch.Tensor, dirs: torch.Tensor, pose: PoseBatch, latent: torch.Tensor | None = None
    ) -> FieldOutput:
        """Evaluate the field.

        Args:
            points: (R, S, 3) world samples along R rays.
            dirs: (R, 3) unit world ray directions.
            pose: per-ray PoseBatch (R entries).
            latent: optional (R, 2 * latent_dim) autoencoder code z = [z_s, z_a].

        Returns:
            FieldOutput; sigma is 0 wherever no part box contains the point.
        """
        inputs = self._inputs(points, dirs, pose, latent)
        out = self._forward(inputs)
        out.sigma = torch.where(inputs.in_box.any(dim=-1), out.sigma, torch.zeros_like(out.sigma))
        return out

    def density(
        self, points: torch.Tensor, dirs: torch.Tensor, pose: PoseBatch, latent: torch.Tensor | None = None
    ) -> torch.Tensor:
        """sigma (R, S) alone, equal to ``forward(...).sigma`` (arguments as :meth:`forward`); fields whose density
        does not need their colour branch skip it (``_density``), e.g. for the occupancy grid's refresh."""
        inputs = self._inputs(points, dirs, pose, latent)
        sigma = self._density(inputs)
        return torch.where(inputs.in_box.any(dim=-1), sigma, torch.zeros_like(sigma))

    def _inputs(self, points, dirs, pose, latent) -> FieldInputs:
        """Validated inputs and the per-part coordinates that ``_forward`` / ``_density`` take."""
        check_shape("points", points, (-1, -1, 3))
        check_shape("dirs", dirs, (points.shape[0], 3))
        if pose.world_from_part.shape[:2] != (points.shape[0], self.n_parts):
            raise ValueError(
                f"pose: expected {points.shape[0]} per-ray entries of {self.n_parts} parts, got "
                f"{tuple(pose.world_from_part.shape[:2])}"
            )
        # fused u (one affine map per ray); x_local, the per-part points, only for the fields that read them
        x_local = part_local(points, dirs, pose)[0] if self.uses_part_points else None
        if self.training:
            dirs, pose = self._perturbed_colour_inputs(dirs, pose)
        d_local = part_directions(dirs, pose)
        u = part_box_coordinates(points, pose, self.box_centres, self.box_half_extents)
        in_box = self.in_parts(u)
        z_s = z_a = None
        if latent is not None and self.latent_dim:
            check_shape("latent", latent, (points.shape[0], 2 * self.latent_dim))
            z_s, z_a = latent[None, :, None, : self.latent_dim], latent[None, :, None, self.latent_dim :]
        if self.appearance_dim:
            z_a = self._appearance(pose)[None, :, None]
        return FieldInputs(points, dirs, pose, x_local, d_local, u, in_box, z_s, z_a)

    def _appearance(self, pose: PoseBatch) -> torch.Tensor:
        """The per-ray appearance codes (R, A) of ``pose``: its own, or zeros where it has none (frames the fit did
        not train on, evaluation)."""
        if pose.appearance is None:
            return pose.reach.new_zeros(pose.reach.shape[0], self.appearance_dim)
        check_shape("pose.appearance", pose.appearance, (pose.reach.shape[0], self.appearance_dim))
        return pose.appearance

    def _perturbed_colour_inputs(self, dirs: torch.Tensor, pose: PoseBatch) -> tuple[torch.Tensor, PoseBatch]:
        """Training only: each ray's direction turned at random (d <- (d + e) / |d + e|, e ~ N(0, view_jitter^2 I),
        so the angle per tangent axis has standard deviation ``view_jitter``) and its pose features zeroed with
        probability ``pose_dropout`` (docs/model.md §4). Neither reaches the density."""
        if self.view_jitter > 0:
            dirs = nn.functional.normalize(dirs + self.view_jitter * torch.randn_like(dirs), dim=-1)
        if self.pose_dropout > 0:
            kept = torch.rand(dirs.shape[0], 1, 1, device=dirs.device) >= self.pose_dropout
            pose = dataclasses.replace(pose, pose_features=pose.pose_features * kept)
        return dirs, pose

    def _density(self, inputs: FieldInputs) -> torch.Tensor:
        return self._forward(inputs).sigma

    def _forward(self, inputs: FieldInputs) -> FieldOutput:
        raise NotImplementedError

    def cost(self) -> Cost:
        """#params (all field parameters), paper-comparable FLOPs and memory per ray, complete FLOPs per ray."""
        params = sum(p.numel() for p in self.parameters())
        flops = complete = memory = 0
        for module in self.modules():
            if isinstance(module, GroupedLinear):
                complete += module.flops()
                if not module.paper_skip:
                    flops += module.flops()
                    memory += module.outputs()
            elif isinstance(module, RadianceHead):
                extra_paper, extra_complete, extra_memory = module.extra_costs()
                flops += extra_paper
                complete += extra_complete
                memory += extra_memory
        complete += self._extra_complete_flops()
        n = SAMPLES_FOR_COST
        return Cost(params, flops * n, memory * n, complete * n)

    def _extra_complete_flops(self) -> int:
        return 0


def masked_softmax(logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Softmax over the last dim restricted to ``mask``; all-zero where nothing is masked in."""
    logits = logits.masked_fill(~mask, float("-inf"))
    has_any = mask.any(dim=-1, keepdim=True)
    probs = torch.softmax(torch.where(has_any, logits, torch.zeros_like(logits)), dim=-1)
    return torch.where(mask, probs, torch.zeros_like(probs))


def rescale_selection(probs: torch.Tensor) -> torch.Tensor:
    """p <- p sqrt(N) / |p| (NARF_D), zero where p is zero."""
    norm = probs.norm(dim=-1, keepdim=True)
    return probs * math.sqrt(probs.shape[-1]) / norm.clamp_min(1e-12)
