"""Building blocks shared by the fields: per-frame pose inputs, part-local coordinates, the radiance head."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import nn

from narf.geometry import check_shape
from narf.layers import EqualLinear, Trunk, WNLinear, density_activation, scaled_unit_rows
from narf.shading import constant_lighting, irradiance


@dataclass
class PoseBatch:
    """Per-frame articulation inputs for B frames (docs/model.md §1).

    Attributes:
        world_from_part: (B, P, 4, 4) part transforms (P = 19 for bodies, 1 for rigid objects).
        reach: (B,) kinematic reach s (body unit).
        bone_lengths: (B, P_zeta) zeta (19 for bodies; may be (B, 0) for rigid objects).
        pose_features: (B, P, 6) xi (se(3) log in the body frame).
        rest_offsets: (B, P, 3) rest joints relative to the pelvis, in body units (D-NARF's t_can).
        world_from_joint: optional (B, 24, 4, 4) all SMPL joints (the CNN baseline's bone maps need the leaves).
        appearance: optional (B, A) per-frame appearance codes (docs/model.md §4, *Per-frame appearance*): training
            frames' only; None (evaluation, new poses) is the zero code.
        light_from_world: optional (B, 3, 3) orthogonal: where a shading field looks its normals up in the lighting
            (docs/model.md §3, *Shading*); None is the identity. A mirror-image body takes the reflection that made
            it, so that its light is the mirror image of the light too (docs/model.md §6, *Left-right symmetry*).
    """

    world_from_part: torch.Tensor
    reach: torch.Tensor
    bone_lengths: torch.Tensor
    pose_features: torch.Tensor
    rest_offsets: torch.Tensor
    world_from_joint: torch.Tensor | None = None
    appearance: torch.Tensor | None = None
    light_from_world: torch.Tensor | None = None

    def __post_init__(self):
        check_shape("world_from_part", self.world_from_part, (-1, -1, 4, 4))
        n_frames, n_parts = self.world_from_part.shape[:2]
        check_shape("reach", self.reach, (n_frames,))
        check_shape("bone_lengths", self.bone_lengths, (n_frames, -1))
        check_shape("pose_features", self.pose_features, (n_frames, n_parts, 6))
        check_shape("rest_offsets", self.rest_offsets, (n_frames, n_parts, 3))
        if self.world_from_joint is not None:
            check_shape("world_from_joint", self.world_from_joint, (n_frames, 24, 4, 4))
        if self.appearance is not None:
            check_shape("appearance", self.appearance, (n_frames, -1))
        if self.light_from_world is not None:
            check_shape("light_from_world", self.light_from_world, (n_frames, 3, 3))

    def _map(self, fn) -> PoseBatch:
        return PoseBatch(*(None if (v := getattr(self, k)) is None else fn(v) for k in self.__dataclass_fields__))

    def select(self, frames: torch.Tensor) -> PoseBatch:
        """Gather per-ray poses: ``frames`` (R,) long -> a PoseBatch of R entries (index_select: where the poses are
        refined, its gradient is an index_add rather than advanced indexing's sort, docs/results/benchmark.md)."""
        return self._map(lambda v: v.index_select(0, frames))

    def to(self, device) -> PoseBatch:
        return self._map(lambda v: v.to(device))

    def detach(self) -> PoseBatch:
        """The same poses without gradient."""
        return self._map(torch.Tensor.detach)


def cat_poses(batches: list[PoseBatch]) -> PoseBatch:
    """The frames of several PoseBatches, one after another: batch k's frame f becomes frame f + (frames of the
    batches before k). Per-frame appearance codes missing from some batches are zeros there (None is the zero code);
    ``world_from_joint`` is kept only when every batch has it (the NARF fields do not read it).

    Args:
        batches: PoseBatches of B_k frames each, with the same parts and appearance size.

    Returns:
        a PoseBatch of sum_k B_k frames.
    """
    first = batches[0]
    codes = [b.appearance for b in batches if b.appearance is not None]
    fields = {}
    for key in first.__dataclass_fields__:
        values = [getattr(b, key) for b in batches]
        if key == "appearance" and codes:
            values = [
                v if v is not None else codes[0].new_zeros(len(b.reach), codes[0].shape[1])
                for v, b in zip(values, batches)
            ]
        if key == "light_from_world" and any(v is not None for v in values):  # None is the identity
            eye = torch.eye(3, dtype=first.reach.dtype, device=first.reach.device)
            values = [v if v is not None else eye.expand(len(b.reach), 3, 3) for v, b in zip(values, batches)]
        fields[key] = None if any(v is None for v in values) else torch.cat(values)
    return PoseBatch(**fields)


def colour_from_nearest_place(pose: PoseBatch, bank: PoseBatch, keep: torch.Tensor) -> PoseBatch:
    """The colour's pose features of frames the fit did not train on, borrowed from the trained frame whose root part
    stands nearest (docs/model.md §4, *Colour of frames not trained on*): frame b not kept takes
    xi_b <- xi_n*, n* = argmin_n ||t_b - t_n|| with t the root part's world position (world_from_part[:, 0, :3, 3];
    ties go to the lowest n). Only ``pose_features`` change: the parts, reach, bones and codes stay the frame's own.

    Args:
        pose: B frames to render.
        bank: N >= 1 frames the fit trained on, with the same parts.
        keep: (B,) bool, frames that are among the trained ones and keep their own xi.

    Returns:
        a PoseBatch of B frames.
    """
    check_shape("keep", keep, (pose.reach.shape[0],))
    check_shape("bank pose_features", bank.pose_features, (-1, *pose.pose_features.shape[1:]))
    if bank.reach.shape[0] == 0:
        raise ValueError("colour_from_nearest_place: the bank of trained frames is empty")
    roots, bank_roots = pose.world_from_part[:, 0, :3, 3], bank.world_from_part[:, 0, :3, 3].to(pose.reach)
    distance = (roots[:, None] - bank_roots[None]).norm(dim=-1)  # (B, N), exact (cdist's matmul path is not)
    borrowed = bank.pose_features.to(pose.pose_features).index_select(0, distance.argmin(dim=1))
    features = torch.where(keep.to(pose.reach.device)[:, None, None], pose.pose_features, borrowed)
    return replace(pose, pose_features=features)


def part_local(points: torch.Tensor, dirs: torch.Tensor, pose: PoseBatch) -> tuple[torch.Tensor, torch.Tensor]:
    """Points and directions in every part frame: x_i = R_i^T (x - t_i) / s, d_i = R_i^T d.

    Args:
        points: (R, S, 3) world samples of R rays.
        dirs: (R, 3) unit world directions.
        pose: per-ray PoseBatch (R entries).

    Returns:
        x_local (R, S, P, 3) in body units, d_local (R, P, 3) unit length.
    """
    rotation = pose.world_from_part[:, :, :3, :3]  # (R, P, 3, 3)
    origin = pose.world_from_part[:, :, :3, 3]  # (R, P, 3)
    # never under bf16 autocast: gamma_10 of the box coordinates needs them to ~1e-4 (2^9 pi u), bf16 keeps ~4e-3
    with torch.autocast(points.device.type, enabled=False):
        offset = points[:, :, None, :] - origin[:, None]  # (R, S, P, 3)
        x_local = torch.einsum("rpji,rspj->rspi", rotation, offset) / pose.reach[:, None, None, None]
        d_local = torch.einsum("rpji,rj->rpi", rotation, dirs)
    return x_local, d_local


def part_box_coordinates(
    points: torch.Tensor, pose: PoseBatch, box_centres: torch.Tensor, box_half_extents: torch.Tensor
) -> torch.Tensor:
    """Box coordinates u_i = (x_i - c_i) / h_i of every sample in every part, as one affine map per ray: the fast
    path of ``(part_local(...)[0] - c) / h`` (:meth:`narf.fields.base.Field.box_coordinates`), its test oracle.

    With a per-ray anchor a (the first part's origin), x_i = R_i^T (x - t_i) / s gives
    u_i = R_i^T (x - a) / (s h_i) - (R_i^T (t_i - a) / s + c_i) / h_i: one (S, 3) x (3, 3P) product per ray. The
    anchor keeps the operands at body scale, so float32 rounding stays ~1e-6 / h like the two-step form.

    Args:
        points: (R, S, 3) world samples. pose: per-ray PoseBatch (R entries). box_centres, box_half_extents: (P, 3).

    Returns:
        u (R, S, P, 3), float32 or wider (never bf16: see :func:`part_local`).
    """
    rotation = pose.world_from_part[:, :, :3, :3]  # (R, P, 3, 3)
    origin = pose.world_from_part[:, :, :3, 3]  # (R, P, 3)
    n_rays, n_parts = origin.shape[:2]
    with torch.autocast(points.device.type, enabled=False):
        anchor = origin[:, :1]  # (R, 1, 3)
        scale = 1 / (pose.reach[:, None, None] * box_half_extents)  # (R, P, 3) per output axis i
        linear = (rotation * scale[:, :, None, :]).permute(0, 2, 1, 3).reshape(n_rays, 3, n_parts * 3)
        shift = torch.einsum("rpji,rpj->rpi", rotation, origin - anchor) * scale + box_centres / box_half_extents
        u = torch.baddbmm(-shift.reshape(n_rays, 1, -1), points - anchor, linear)
    return u.reshape(*points.shape[:2], n_parts, 3)


def part_directions(dirs: torch.Tensor, pose: PoseBatch) -> torch.Tensor:
    """d_i = R_i^T d per part: dirs (R, 3) -> (R, P, 3) (as :func:`part_local`). No gradient reaches the part
    rotations through d_i: a corrected pose (docs/model.md §6) must answer where the body is, not which colour a
    turned view direction would give it (as the pose features xi, which are detached too)."""
    with torch.autocast(dirs.device.type, enabled=False):
        return torch.einsum("rpji,rj->rpi", pose.world_from_part[:, :, :3, :3].detach(), dirs)


class RadianceHead(nn.Module):
    """Trunk, density and colour branch (docs/model.md §3), over ``groups`` independent copies.

    Density: e = sum_k W_k X_k (+ W_s z_s) -> trunk -> sigma = act(Lin_{H->1}(h)).
    Colour: h1 = LReLU_0.2(sqrt(H) h/|h| + W_a z_a); h2 = Lin_{H->H/2}(h1);
    h3 = LReLU_0.2(h2 + sum_k W_k Y_k); c = sigmoid(Lin_{H/2->3}(h3)).

    Inputs are (G, R, S, dim) per sample or (G, R, 1, dim) per ray (embedded once, then broadcast). With
    ``group_index`` (G',) the inputs are G' blocks, block b going through head ``group_index[b]`` (ragged groups
    packed in equal blocks, NARF_P's fast path).

    Args:
        density_dims / color_dims: input block name -> width.
        width: H.
        groups: G independent heads (NARF_P: 19).
        latent_dim: size of z_s and z_a (0: no autoencoder latents).
        appearance_dim: size of a per-frame appearance code, which takes z_a's place (W_a z_a; 0: none). A head has
            the autoencoder's latents or a per-frame code, never both.
        density_act: ``leaky_backward`` or ``softplus``.
        trunk_blocks: the trunk's residual blocks B (:class:`narf.layers.Trunk`; the paper: 3).
        shading: c = albedo E(n_L) (docs/model.md §3, *Shading*; not in the paper): the colour above is the albedo,
            the head also predicts a normal n from h1, in the frame that the caller's ``rotation`` turns into the
            lighting's, and learns the lighting E (``narf.shading``, 9 coefficients a channel).
    """

    def __init__(
        self,
        density_dims: dict[str, int],
        color_dims: dict[str, int],
        width: int,
        groups: int = 1,
        latent_dim: int = 0,
        density_act: str = "leaky_backward",
        appearance_dim: int = 0,
        trunk_blocks: int = 3,
        shading: bool = False,
    ):
        super().__init__()
        if latent_dim and appearance_dim:
            raise ValueError("a radiance head takes the autoencoder's latents or a per-frame appearance code, not both")
        self.width, self.groups, self.latent_dim = width, groups, latent_dim
        self.density_embed = nn.ModuleDict({k: WNLinear(d, width, groups) for k, d in density_dims.items()})
        self.color_embed = nn.ModuleDict({k: WNLinear(d, width // 2, groups) for k, d in color_dims.items()})
        self.latent_shape = EqualLinear(latent_dim, width, groups) if latent_dim else None
        code_dim = latent_dim or appearance_dim
        self.latent_appearance = EqualLinear(code_dim, width, groups) if code_dim else None
        self.trunk = Trunk(width, groups, trunk_blocks)
        self.sigma_out = WNLinear(width, 1, groups)
        self.color_hidden = WNLinear(width, width // 2, groups, paper_skip=True)
        self.rgb_out = WNLinear(width // 2, 3, groups)
        self.density_act = density_activation(density_act)
        self.normal_out = WNLinear(width, 3, groups, paper_skip=True) if shading else None
        self.lighting = nn.Parameter(constant_lighting()) if shading else None

    @staticmethod
    def _embed(layer, inputs: torch.Tensor, group_index: torch.Tensor | None = None) -> torch.Tensor:
        g, r, s, d = inputs.shape
        return layer(inputs.reshape(g, r * s, d), group_index).reshape(g, r, s, layer.out_features)

    def _embed_sum(self, layers: nn.ModuleDict, inputs: dict[str, torch.Tensor], group_index=None) -> torch.Tensor:
        total = None
        for name, value in inputs.items():
            embedded = self._embed(layers[name], value, group_index)
            total = embedded if total is None else total + embedded
        return total

    def forward(
        self,
        density_inputs: dict[str, torch.Tensor],
        color_inputs: dict[str, torch.Tensor],
        z_s: torch.Tensor | None = None,
        z_a: torch.Tensor | None = None,
        group_index: torch.Tensor | None = None,
        rotation: torch.Tensor | None = None,
    ):
        """Returns sigma (G, R, S) and rgb (G, R, S, 3). Latents are (G or 1, R, 1, latent_dim); ``rotation``: with
        shading, (G or 1, R, S, 3, 3) light_from_normal of each sample (see ``forward_embedded``)."""
        embedded = self._embed_sum(self.density_embed, density_inputs, group_index)
        colour = self._embed_sum(self.color_embed, color_inputs, group_index)
        return self.forward_embedded(embedded, colour, {}, z_s, z_a, group_index, rotation)

    def forward_embedded(
        self,
        embedded: torch.Tensor,
        color_embedded: torch.Tensor,
        extra_density: dict[str, torch.Tensor],
        z_s=None,
        z_a=None,
        group_index: torch.Tensor | None = None,
        rotation: torch.Tensor | None = None,
    ):
        """As ``forward`` from already embedded sums (G, R, S or 1, H) and (G, R, S or 1, H/2); blocks in
        ``extra_density`` are embedded and added here. With shading, ``rotation`` (G or 1, R, S, 3, 3) turns the
        predicted normal into the lighting's frame (NARF_D: the selector's blend of the part rotations), and is
        required."""
        n_samples = max(embedded.shape[2], color_embedded.shape[2])
        hidden, sigma = self._trunk(embedded, extra_density, z_s, n_samples, group_index)
        h1 = scaled_unit_rows(hidden, math.sqrt(self.width), 1e-6).reshape(*sigma.shape, self.width)
        if self.latent_appearance is not None and z_a is not None:
            h1 = h1 + self._embed(self.latent_appearance, z_a.expand(sigma.shape[0], -1, -1, -1), group_index)
        # in place: h1 and the sum are fresh tensors used once
        a1 = nn.functional.leaky_relu(h1, 0.2, inplace=True)
        h2 = self._embed(self.color_hidden, a1, group_index)
        h3 = nn.functional.leaky_relu(h2 + color_embedded, 0.2, inplace=True)
        rgb = torch.sigmoid(self._embed(self.rgb_out, h3, group_index))
        if self.lighting is not None:
            rgb = rgb * self._shading(a1, rotation, group_index)
        return sigma, rgb

    def _shading(self, a1: torch.Tensor, rotation: torch.Tensor | None, group_index) -> torch.Tensor:
        """E(n_L) (G, R, S, 3) of the normals n_L = normalise(rotation n), n = Lin_{H->3}(a1) (docs/model.md §3)."""
        if rotation is None:
            raise ValueError("a shading head needs each sample's rotation into the lighting's frame")
        normal = self._embed(self.normal_out, a1, group_index)  # (G, R, S, 3) in the rotation's frame
        lit = nn.functional.normalize((rotation.to(normal.dtype) @ normal[..., None])[..., 0], dim=-1, eps=1e-6)
        return irradiance(lit, self.lighting.to(lit.dtype))

    def density_embedded(
        self, embedded: torch.Tensor, extra_density: dict[str, torch.Tensor], z_s=None, group_index=None
    ) -> torch.Tensor:
        """sigma (G, R, S) alone, as ``forward_embedded`` without the colour branch (the density does not read it)."""
        return self._trunk(embedded, extra_density, z_s, embedded.shape[2], group_index)[1]

    def _trunk(self, embedded, extra_density, z_s, n_samples: int, group_index):
        """Density input sum -> trunk features (G, R*S, H) and sigma (G, R, S), S = ``n_samples``."""
        if extra_density:
            embedded = embedded + self._embed_sum(self.density_embed, extra_density, group_index)
        if self.latent_shape is not None and z_s is not None:
            embedded = embedded + self._embed(self.latent_shape, z_s.expand(embedded.shape[0], -1, -1, -1), group_index)
        embedded = embedded.expand(-1, -1, n_samples, -1)
        g, r, s, h = embedded.shape
        hidden = self.trunk(embedded.reshape(g, r * s, h), group_index)
        return hidden, self.density_act(self.sigma_out(hidden, group_index))[..., 0].reshape(g, r, s)

    def extra_costs(self) -> tuple[int, int, int]:
        """(paper FLOPs, complete FLOPs, memory) beyond the linear layers: ReLUs, residual adds, feature sums."""
        n_sums = len(self.density_embed) - 1 + (1 if self.latent_shape is not None else 0)
        paper = self.trunk.extra_flops() + self.groups * self.width * n_sums
        half = self.width // 2
        colour = self.groups * (self.width + half + half * len(self.color_embed) + self.width)  # lrelu x2, sums, norm
        return paper, paper + colour, self.trunk.extra_memory()
