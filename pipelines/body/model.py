"""SMPL body model glue: ZJU-style parameters -> posed vertices, part transforms, zeta, xi, part boxes.

Model files are read here (pipelines); the kinematics are the pure functions of ``narf.kinematics``. The
ZJU / EasyMocap convention is ``V_world = R(Rh) X + Th`` with ``X = SMPL(poses, shapes)`` without translation
(docs/formats.md §1.6).
"""

from __future__ import annotations

import contextlib
import functools
import io
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import smplx
import torch
from smplx.lbs import batch_rigid_transform, batch_rodrigues, lbs
from smplx.utils import Struct

from fitting.corrections import CapturePoses
from fitting.mesh import vertex_normals
from narf.fields.common import PoseBatch
from narf.geometry import so3_log
from narf.kinematics import (
    N_JOINTS,
    bone_lengths,
    fit_part_boxes,
    kinematic_reach,
    part_pose_features,
    parts_from_joints,
    rigid_from_rotvec_translation,
    vertex_parts,
    world_from_joints,
)
from pipelines.body.locate import resolve_smpl_file
from pipelines.datasets.smpl_files import load_smpl_dict


@dataclass
class PosedBody:
    """A batch of posed bodies (B frames), everything in world units.

    Attributes:
        vertices: (B, V, 3) world vertices.
        world_from_joint: (B, 24, 4, 4) chained rotation, origin at the posed joint.
        world_from_part: (B, 19, 4, 4) the NARF parts (joints with children).
        rest_joints: (B, 24, 3) rest joints in the SMPL frame (shape applied).
        bone_lengths: (B, 19) zeta.
        reach: (B,) kinematic reach s.
        pose_features: (B, 19, 6) xi = se(3) log of each part in the body frame (divide by pi to encode).
    """

    vertices: torch.Tensor
    world_from_joint: torch.Tensor
    world_from_part: torch.Tensor
    rest_joints: torch.Tensor
    bone_lengths: torch.Tensor
    reach: torch.Tensor
    pose_features: torch.Tensor


def _as_tensor(name: str, value, shape_tail: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
    """``value`` as a (B, *shape_tail) tensor of ``dtype`` (tensors keep their gradient), checked."""
    tensor = value.to(dtype) if isinstance(value, torch.Tensor) else torch.as_tensor(np.asarray(value), dtype=dtype)
    if tensor.ndim == len(shape_tail):
        tensor = tensor[None]
    if tensor.ndim != len(shape_tail) + 1 or tuple(tensor.shape[1:]) != shape_tail:
        raise ValueError(f"{name}: expected shape (B, {', '.join(map(str, shape_tail))}), got {tuple(tensor.shape)}")
    if not torch.isfinite(tensor).all():
        raise ValueError(f"{name}: contains NaN or infinite values")
    return tensor


class BodyModel:
    """An SMPL-format body model (a user's SMPL or the generated stand-in).

    Args:
        smpl_path: model file or folder; ``None`` resolves ``$NARF_SMPL_DIR`` then the stand-in.
        dtype: float32 (default) or float64.
    """

    def __init__(self, smpl_path: str | Path | None = None, dtype: torch.dtype = torch.float32):
        self.path = resolve_smpl_file(smpl_path)
        self.dtype = dtype
        data = load_smpl_dict(self.path)
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):  # smplx prints a beta warning
            warnings.simplefilter("ignore")
            self.smpl = smplx.SMPL(str(self.path), data_struct=Struct(**data), dtype=dtype, num_betas=10)
        self.faces = np.asarray(data["f"]).astype(np.int64)
        self.skinning_weights = self.smpl.lbs_weights
        self.parts_of_vertices = vertex_parts(self.skinning_weights)
        self._posedirs: dict[int, torch.Tensor] = {}

    @property
    def n_vertices(self) -> int:
        return self.smpl.v_template.shape[0]

    def rest_joints(self, betas: torch.Tensor) -> torch.Tensor:
        """(B, 10) betas -> (B, 24, 3) rest joints ``J_regressor (v_template + shapedirs beta)``."""
        v_shaped = self.smpl.v_template + smplx.lbs.blend_shapes(betas, self.smpl.shapedirs)
        return smplx.lbs.vertices2joints(self.smpl.J_regressor, v_shaped)

    def pose_zju(self, poses, rh, th, shapes, pose_blendshapes: bool = True, template_offsets=None) -> PosedBody:
        """Pose ZJU-MoCap parameters.

        Args:
            poses: (B, 72) axis-angle (``poses[:, :3]`` is usually 0; the global orientation is in Rh).
            rh: (B, 3) global rotation vector, about the SMPL origin.
            th: (B, 3) global translation, metres.
            shapes: (B, 10) betas.
            pose_blendshapes: False for the old ``params/`` fits (no pose blend shapes).
            template_offsets: optional (6890, 3) rest-frame offsets of the surface (:meth:`vertices_zju`).

        Returns:
            A :class:`PosedBody`.
        """
        poses = _as_tensor("poses", poses, (72,), self.dtype)
        rh = _as_tensor("Rh", rh, (3,), self.dtype)
        th = _as_tensor("Th", th, (3,), self.dtype)
        shapes = _as_tensor("shapes", shapes, (10,), self.dtype)
        if not poses.shape[0] == rh.shape[0] == th.shape[0] == shapes.shape[0]:
            raise ValueError(
                f"batch sizes differ: poses {poses.shape[0]}, Rh {rh.shape[0]}, Th {th.shape[0]}, "
                f"shapes {shapes.shape[0]}"
            )
        world_from_smpl = rigid_from_rotvec_translation(rh, th)
        if template_offsets is not None:  # the skeleton stays the shape's: smplx's lbs would regress it from them
            vertices = self.vertices_zju(poses, rh, th, shapes, 1, pose_blendshapes, template_offsets)
            return posed_from_rest_joints(poses, world_from_smpl, self.rest_joints(shapes), vertices)
        posedirs = self.smpl.posedirs if pose_blendshapes else torch.zeros_like(self.smpl.posedirs)
        vertices_smpl, _ = lbs(
            shapes,
            poses,
            self.smpl.v_template,
            self.smpl.shapedirs,
            posedirs,
            self.smpl.J_regressor,
            self.smpl.parents,
            self.smpl.lbs_weights,
        )
        vertices = vertices_smpl @ world_from_smpl[:, :3, :3].transpose(1, 2) + th[:, None]
        return posed_from_rest_joints(poses, world_from_smpl, self.rest_joints(shapes), vertices)

    def vertices_zju(
        self, poses, rh, th, shapes, every: int = 1, pose_blendshapes: bool = True, template_offsets=None
    ) -> torch.Tensor:
        """Every ``every``-th vertex of :meth:`pose_zju`'s posed body, (B, ceil(6890 / every), 3) world: smplx's
        ``lbs`` step by step (shape and pose blend shapes, ``batch_rigid_transform``, skinning) on those vertices
        alone, the joints regressed from the whole shaped mesh. For fits that pose many frames many times and look
        at a subset of the surface (``pipelines.body.silhouettes``).

        ``template_offsets`` (6890, 3), rest-frame metres: added to the shaped template before the pose blend shapes
        and the skinning, the skeleton left as the shape makes it (SMPL+D, docs/guides/real-captures.md, "Body
        fit")."""
        m = self.smpl
        batch = poses.shape[0]
        template, weights = m.v_template[::every], m.lbs_weights[::every]
        shapedirs = m.shapedirs[::every]
        v_shaped = template + smplx.lbs.blend_shapes(shapes, shapedirs)
        if template_offsets is not None:
            v_shaped = v_shaped + template_offsets[::every]
        rotations = batch_rodrigues(poses.reshape(-1, 3)).reshape(batch, N_JOINTS, 3, 3)
        if pose_blendshapes:
            eye = torch.eye(3, dtype=poses.dtype, device=poses.device)
            features = (rotations[:, 1:] - eye).reshape(batch, -1)
            v_shaped = v_shaped + (features @ self._strided_posedirs(every)).reshape(batch, -1, 3)
        _, transforms = batch_rigid_transform(rotations, self.rest_joints(shapes), m.parents)
        skin = (weights @ transforms.reshape(batch, N_JOINTS, 16)).reshape(batch, -1, 4, 4)
        local = (skin[..., :3, :3] @ v_shaped[..., None])[..., 0] + skin[..., :3, 3]
        world_from_smpl = rigid_from_rotvec_translation(rh, th)
        return local @ world_from_smpl[:, :3, :3].transpose(1, 2) + th[:, None]

    def _strided_posedirs(self, every: int) -> torch.Tensor:
        """(207, 3 ceil(6890 / every)) the pose blend shapes of every ``every``-th vertex, copied once (a strided
        view's reshape copied the 8 MB on each call)."""
        if every not in self._posedirs:
            posedirs = self.smpl.posedirs
            self._posedirs[every] = posedirs.reshape(posedirs.shape[0], -1, 3)[:, ::every].reshape(
                posedirs.shape[0], -1
            )
        return self._posedirs[every]

    @functools.cached_property
    def template_normals(self) -> torch.Tensor:
        """(6890, 3) unit vertex normals of the mean template (``fitting.mesh.vertex_normals``), the directions of a
        fit's per-vertex displacement (``pipelines.prepare.body.fit``)."""
        normals = vertex_normals(self.smpl.v_template.double().numpy(), self.faces)
        return torch.as_tensor(normals, dtype=self.dtype)

    def surface_offsets(self, displacement) -> torch.Tensor | None:
        """(6890, 3) rest-frame offsets ``d_i n_i`` of a (6890,) displacement along :attr:`template_normals`
        (metres; a capture's ``body_surface.npy``, docs/formats.md §1.13), or None for None."""
        if displacement is None:
            return None
        return torch.as_tensor(displacement, dtype=self.dtype)[:, None] * self.template_normals

    def rest_body(self, shapes, template_offsets=None) -> PosedBody:
        """The rest pose (identity rotations, no global transform) for the given betas."""
        shapes = _as_tensor("shapes", shapes, (10,), self.dtype)
        zeros = torch.zeros(shapes.shape[0], 3, dtype=self.dtype)
        poses = torch.zeros(shapes.shape[0], 72, dtype=self.dtype)
        return self.pose_zju(poses, zeros, zeros, shapes, template_offsets=template_offsets)

    def part_boxes(self, bodies: list[PosedBody], scale_pad: float = 1.1, abs_pad: float = 0.03):
        """Fit part boxes over the rest pose(s) and the given posed frames (use at most 100 training frames).

        Returns:
            centres (19, 3), half_extents (19, 3) in body units.
        """
        vertices = torch.cat([b.vertices for b in bodies])
        world_from_part = torch.cat([b.world_from_part for b in bodies])
        reach = torch.cat([b.reach for b in bodies])
        return fit_part_boxes(vertices, world_from_part, reach, self.parts_of_vertices, scale_pad, abs_pad)


def posed_from_rest_joints(
    poses: torch.Tensor, world_from_smpl: torch.Tensor, rest_joints: torch.Tensor, vertices: torch.Tensor | None = None
) -> PosedBody:
    """Forward kinematics of a (possibly edited) rest skeleton into a PosedBody.

    Args:
        poses: (B, 72) axis-angle. world_from_smpl: (B, 4, 4). rest_joints: (B, 24, 3).
        vertices: (B, V, 3) posed vertices if known (an empty tensor otherwise).
    """
    world_from_joint = world_from_joints(poses.reshape(-1, N_JOINTS, 3), rest_joints, world_from_smpl)
    world_from_part = parts_from_joints(world_from_joint)
    joints = world_from_joint[..., :3, 3]
    reach = kinematic_reach(joints)
    return PosedBody(
        vertices=torch.empty(0) if vertices is None else vertices,
        world_from_joint=world_from_joint,
        world_from_part=world_from_part,
        rest_joints=rest_joints,
        bone_lengths=bone_lengths(joints),
        reach=reach,
        pose_features=part_pose_features(world_from_part, reach),
    )


def smplx_params_from_zju(model: BodyModel, poses, rh, th, shapes) -> dict[str, torch.Tensor]:
    """Convert ZJU parameters to smplx ``SMPL.forward`` keywords (docs/formats.md §1.6).

    global_orient = rotvec(R(Rh) R(poses[:3])); body_pose = poses[3:]; betas = shapes;
    transl = Th + R(Rh) J0 - J0 with J0 the shaped rest pelvis.
    """
    poses = _as_tensor("poses", poses, (72,), model.dtype)
    rh = _as_tensor("Rh", rh, (3,), model.dtype)
    th = _as_tensor("Th", th, (3,), model.dtype)
    shapes = _as_tensor("shapes", shapes, (10,), model.dtype)
    rot_rh = rigid_from_rotvec_translation(rh, torch.zeros_like(rh))[:, :3, :3]
    rot_root = rigid_from_rotvec_translation(poses[:, :3], torch.zeros_like(rh))[:, :3, :3]
    pelvis = model.rest_joints(shapes)[:, 0]
    transl = th + (rot_rh @ pelvis[..., None])[..., 0] - pelvis
    return {"global_orient": so3_log(rot_rh @ rot_root), "body_pose": poses[:, 3:], "betas": shapes, "transl": transl}


def pose_batch(body: PosedBody) -> PoseBatch:
    """The model inputs of posed bodies: part transforms, reach, zeta, xi and rest offsets (J_i - J_0)/s."""
    from narf.kinematics import PART_JOINTS

    rest = body.rest_joints[:, list(PART_JOINTS)]
    offsets = (rest - body.rest_joints[:, :1]) / body.reach[:, None, None]
    return PoseBatch(
        body.world_from_part, body.reach, body.bone_lengths, body.pose_features, offsets, body.world_from_joint
    )


def pose_batch_from_joints(world_from_joint: torch.Tensor) -> PoseBatch:
    """Model inputs from posed joint frames alone (NARF's THUman ``pose_to_world``, SURREAL bodies): the rest
    skeleton is recovered from the chain (``narf.kinematics.rest_offsets_from_world``).

    Args:
        world_from_joint: (B, 24, 4, 4) chained rotations with the posed joints as origins.
    """
    from narf.kinematics import PART_JOINTS, rest_offsets_from_world

    world_from_part = parts_from_joints(world_from_joint)
    joints = world_from_joint[..., :3, 3]
    reach = kinematic_reach(joints)
    rest = rest_offsets_from_world(world_from_joint)[:, list(PART_JOINTS)]
    return PoseBatch(
        world_from_part,
        reach,
        bone_lengths(joints),
        part_pose_features(world_from_part, reach),
        rest / reach[:, None, None],
        world_from_joint,
    )


def capture_poses(source, body_model: BodyModel, frames: list[int]) -> CapturePoses:
    """The body parameters of ``frames`` of ``source`` (anything with ``params(frame)``: a capture, a loaded run) that
    pose correction starts from (``fitting.corrections``)."""
    params = [source.params(f) for f in frames]
    poses, rh, th, shapes = (
        torch.as_tensor(np.stack([getattr(p, k) for p in params]), dtype=body_model.dtype)
        for k in ("poses", "rh", "th", "shapes")
    )
    with torch.no_grad():
        rest_joints = body_model.rest_joints(shapes)
    world_from_smpl = rigid_from_rotvec_translation(rh, th)
    return CapturePoses(poses.reshape(-1, 24, 3), world_from_smpl, rest_joints, torch.as_tensor(frames))
