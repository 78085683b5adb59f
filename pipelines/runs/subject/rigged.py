"""A fitted avatar as a rigged glTF (``narf-export-mesh --rigged``): docs/design.md *Rigged export*.

* **Bind pose.** The body model's rest pose (every joint rotation zero) with the subject's shape, or a capture frame
  (``--frame N``). The mesh is extracted there (marching cubes at the fit's level, colours as for static meshes).
* **Skeleton.** The body model's 24 joints with their names (SMPL order); bone j's global transform is
  ``world_from_joint`` (chained rotation, origin at the posed joint), the frames NARF's parts move with.
* **Skin.** NARF's parts are rigid: part p moves with ``world_from_part[p]``, the joint ``PART_JOINTS[p]``. A vertex
  takes the part selector's four most probable parts, renormalised (``--skin selector``), or its most probable part
  alone (``--skin rigid``: exactly the field's rigid motion of that part). A vertex the selector gives no part
  (outside every part box) and every vertex of a field without a selector follow the part whose box holds them most
  deeply.
* **Frame.** glTF is y-up, metres, facing +z. The export frame puts the capture's floor at y = 0 with its up axis
  along +y, the stage centre at the origin and the subject's mean facing along +z (``pipelines.body.motion.Stage``);
  the rest pose is stood on the same floor at the origin, facing +z.
* **Motion.** ``--motion FILE`` is placed on the capture's stage as ``narf-render-video`` places it and baked as one
  animation: every joint's local rotation and translation per frame at ``--fps``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from fitting.files import atomic_write_bytes
from fitting.fitted import SavedRun, run_folder
from fitting.mesh import extract_mesh, vertex_normals
from narf.extraction import nearest_part, query_points
from narf.fields import model_spec
from narf.kinematics import JOINT_NAMES, PART_JOINTS, SMPL_PARENTS
from pipelines.body.model import pose_batch
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.gltf import Animation, Skeleton, SkinnedMesh, skinned_glb
from pipelines.runs.requests import ExportRequest, MotionClip
from pipelines.runs.subject.mesh import resolve_level
from pipelines.runs.subject.session import load_run
from pipelines.runs.subject.video import capture_stage, motion_params

SKINS = ("selector", "rigid")


def export_from_world(stage) -> np.ndarray:
    """(4, 4) the export frame from the capture's world: up -> +y, mean facing -> +z, stage centre on the floor -> 0."""
    facing = stage.forward if np.linalg.norm(stage.forward) > 0 else np.cross(stage.up, [1.0, 0.0, 0.0])
    rotation = Rotation.align_vectors([[0, 1.0, 0], [0, 0, 1.0]], [stage.up, facing], weights=[np.inf, 1])[0]
    origin = stage.centre - (stage.centre @ stage.up - stage.floor) * stage.up
    out = np.eye(4)
    out[:3, :3] = rotation.as_matrix()
    out[:3, 3] = -out[:3, :3] @ origin
    return out


def skin_weights(part_probs: np.ndarray, skin: str) -> tuple[np.ndarray, np.ndarray]:
    """(V, P) part probabilities -> joints (V, 4) and weights (V, 4) of the four most probable parts, renormalised
    (``selector``), or the most probable part with weight one (``rigid``)."""
    order = np.argsort(-part_probs, axis=1, kind="stable")[:, :4]
    weights = np.take_along_axis(part_probs, order, axis=1).astype(np.float64)
    if skin == "rigid":
        weights = np.zeros_like(weights)
        weights[:, 0] = 1
    else:
        weights = weights / np.maximum(weights.sum(axis=1, keepdims=True), 1e-12)
    joints = np.asarray(PART_JOINTS)[order]
    joints[weights == 0] = 0  # unused slots point at the root with weight zero
    return joints.astype(np.uint16), weights.astype(np.float32)


def _bind_pose(run, frame: int | None, stage_from_world: np.ndarray, shapes: torch.Tensor):
    """Body of the bind pose (field world) and the export frame from that world."""
    body_model = run.body_model
    if frame is None:
        with torch.no_grad():
            body = body_model.rest_body(shapes[:1].to(body_model.dtype))
        vertices = body.vertices[0].double().numpy()
        shift = np.eye(4)  # the rest pose is y-up and faces +z already: stand it on y = 0 over the origin
        shift[:3, 3] = [-body.world_from_joint[0, 0, 0, 3].item(), -vertices[:, 1].min(), -vertices[:, 2].mean()]
        return body, shift
    if not 0 <= frame < run.capture.n_frames:
        raise CaptureError(f"{run.capture.root}: frame {frame} out of range (0..{run.capture.n_frames - 1})")
    p = run.params(frame)
    with torch.no_grad():
        body = body_model.pose_zju(*(torch.as_tensor(v)[None] for v in (p.poses, p.rh, p.th, p.shapes)))
    return body, stage_from_world


def _animation(run, request: ExportRequest, staged, stage_from_world) -> tuple[Animation, dict]:
    """The request's motion window as the skeleton's animation in the export frame, and the motion's report."""
    start, stop = request.window or (0, None)
    n_frames = None if stop is None else stop - start
    clip = MotionClip(Path(request.motion), start, n_frames, request.fps, request.motion_fps, "--frames")
    params, report = motion_params(run, clip, staged)
    stack = [torch.as_tensor(np.stack([getattr(p, k) for p in params])) for k in ("poses", "rh", "th", "shapes")]
    with torch.no_grad():
        world_from_joint = run.body_model.pose_zju(*stack).world_from_joint.double().numpy()
    times = np.arange(len(params)) / report["fps"]
    return Animation(times, stage_from_world @ world_from_joint), report


def export_rigged(run: Path | SavedRun, request: ExportRequest) -> tuple[Path, dict]:
    """Write the rigged glb (module docstring); returns its path and a record (level, vertices, frames)."""
    r = request
    out, skin, device = Path(r.out), r.skin, r.device
    if out.suffix.lower() != ".glb":
        raise ValueError(f"{out}: a rigged export is glTF binary; name it .glb")
    if skin not in SKINS:
        raise ValueError(f"--skin must be one of {', '.join(SKINS)}, got '{skin}'")
    run_dir = run_folder(run)
    run = load_run(run, device)
    if not model_spec(run.config.model.name).meshes:
        raise ValueError(f"{run_dir}: the CNN baseline renders images, not a density field: no mesh to export")
    staged = capture_stage(run)
    stage, _, shapes = staged
    stage_from_world = export_from_world(stage)
    body, bind_from_world = _bind_pose(run, r.frame, stage_from_world, shapes)
    animation = report = None
    if r.motion is not None:
        animation, report = _animation(run, r, staged, stage_from_world)
    level, record = resolve_level(run, r.level, device)
    pose = run.colour_poses(pose_batch(body), None if r.frame is None else [r.frame]).to(device)  # docs/model.md §4
    mesh = extract_mesh(run.field, pose, r.resolution, level, progress=r.progress)
    points = torch.as_tensor(mesh.vertices, dtype=torch.float32, device=device)
    probs = query_points(run.field, points, pose)["part_probs"]
    if probs is None:  # a field without a part selector: every vertex follows the part whose box holds it deepest
        probs = torch.zeros(len(points), len(PART_JOINTS), device=device)
    unassigned = probs.sum(dim=1) <= 1e-6  # outside every part box the selector gives nothing
    if unassigned.any():
        deepest = nearest_part(run.field, points[unassigned], pose)
        probs[unassigned] = torch.nn.functional.one_hot(deepest, len(PART_JOINTS)).to(probs.dtype)
    joints, weights = skin_weights(probs.cpu().double().numpy(), skin)
    rotation, shift = bind_from_world[:3, :3], bind_from_world[:3, 3]
    vertices = mesh.vertices @ rotation.T + shift
    skinned = SkinnedMesh(vertices, vertex_normals(vertices, mesh.faces), mesh.faces, mesh.colours, joints, weights)
    bind = bind_from_world @ body.world_from_joint[0].double().numpy()
    skeleton = Skeleton(JOINT_NAMES, SMPL_PARENTS, bind)
    atomic_write_bytes(out, skinned_glb(skinned, skeleton, animation))
    frames = 0 if animation is None else len(animation.times)
    return out, record | {"vertices": len(vertices), "faces": len(mesh.faces), "frames": frames, "motion": report}
