"""Multi-view body fit: the body model's joints to triangulated targets and 2D keypoints, as EasyMocap's
multi-view SMPL fit does (docs/guides/real-captures.md, "Body fit").

Minimised over per-frame ``Rh, Th, poses`` (ZJU convention ``V = R(Rh) X + Th``, ``poses[:3] = 0``), one shape for
the sequence, and one learned offset per detector point that is not a joint centre (hips, shoulders, neck, head,
feet; mirrored left/right, in the joint's frame):

``E = w3 sum rho(|J - X| / s3) + w2 sum c rho(|pi(J) - x| / (s2 h)) + wp |theta|^2_W + ws (|d theta|^2 + |d Th|^2)
+ wb |beta|^2 + wo |offset|^2``

with ``rho(r) = r^2 / (r^2 + 1)`` (Geman-McClure), ``c`` the detector confidence, ``h`` the image height, ``W`` heavier
on joints that no target observes (wrists, hands, feet, head), and ``d`` the frame-to-frame difference. Joints
need no vertices (they are regressed from the shaped rest mesh, before pose blend shapes), so each step is one
forward kinematics pass.

*Graduated reach.* Every frame starts from the rest pose, and Geman-McClure stops pulling a target more than a few
scales away: a limb far from rest in a fast movement (an arm overhead, a leg kicked back) then follows the priors and
the neighbouring frames instead of its keypoints. The pose stage therefore starts with the kernel
``rho_k(r) = r^2 / (1 + (r / k)^2)`` at ``k = robust_reach`` (as steep near zero, saturating k times further out) and
shrinks k geometrically to 1 (Geman-McClure) over its first half, a graduated non-convexity
(docs/guides/real-captures.md, step 6); the global stage, where the limbs are still at rest, keeps k = 1.

A last stage (``silhouette_iterations``) adds the person masks, ``w_s (E_out + E_in)`` of
``pipelines.prepare.body.masks`` on the posed vertices, and corrects every camera's pose
(:class:`CameraCorrection`) against a prior of ``camera_turn`` degrees and ``camera_shift`` metres: a calibration a
few pixels off moves every view's silhouette the same way in every frame, which no body pose can absorb. With
``surface``, that stage also fits one displacement ``d_i`` of every template vertex along its normal, shared by
all frames (SMPL+D: clothes and build that ten shape coefficients miss), with the prior of :class:`SurfacePrior`;
the skeleton stays the shape's, so the part transforms a subject fit learns in do not move.

A take longer than ``window`` frames goes through that stage in pieces, so that its memory (each view's distance map
and the autograd graph of the posed vertices) does not grow with the take: first ``window`` frames spread over the
take fit the shape, the offsets and the cameras (no smoothness: they are not neighbours); then overlapping windows of
``window`` consecutive frames fit their own poses with those held, each window's smoothness reaching across its seam
to the last frame the previous window keeps (docs/guides/real-captures.md, "Body fit").
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace

import numpy as np
import torch
from smplx.lbs import batch_rodrigues

from narf.kinematics import N_JOINTS, rigid_from_rotvec_translation, world_from_joints
from pipelines.body.model import BodyModel
from pipelines.body.silhouettes import adam_stage
from pipelines.datasets.keypoints import TARGET_JOINTS, TARGETS, mirror_index

#: joints whose rotation moves no target: held near rest by a stronger prior
UNOBSERVED_JOINTS = (10, 11, 15, 20, 21, 22, 23)
TORSO_TARGETS = ("l_hip", "r_hip", "l_shoulder", "r_shoulder", "pelvis", "neck")


@dataclass(frozen=True)
class FitSettings:
    """Weights and scales of the body fit (module docstring)."""

    iterations: int = 500
    global_iterations: int = 100
    lr: float = 0.03
    scale_3d: float = 0.05  # metres: residuals beyond ~5 cm count less and less (robust)
    scale_2d: float = 0.02  # fraction of the image height
    weight_3d: float = 1.0
    weight_2d: float = 1.0
    pose_prior: float = 2e-3
    unobserved_prior: float = 0.1
    smooth: float = 0.5
    robust_reach: float = 4.0  # the keypoint stage's robust kernel starts saturating this many times further out
    shape_prior: float = 1e-3
    offset_prior: float = 5.0
    silhouette_iterations: int = 400  # the last stage, when the masks take part (pipelines.prepare.body.masks)
    silhouette_lr: float = 0.02
    silhouette_weight: float = 30.0
    refine_cameras: bool = True  # the last stage also corrects each camera's pose (CameraCorrection)
    camera_turn: float = 1.0  # degrees: the camera prior's scale of turns ...
    camera_shift: float = 0.01  # ... and of shifts (metres)
    window: int = 100  # frames the silhouette stage holds at once (0: every frame, whatever the take's length)
    window_overlap: int = 10  # frames a window fits again of the previous one's end (at most half a window)
    surface: bool = True  # the silhouette stage also fits a displacement of each vertex along its normal (SMPL+D)
    surface_scale: float = 0.01  # metres: the displacement's unit
    surface_prior: float = 0.1  # weight of mean (d / scale)^2 ...
    surface_smooth: float = 10.0  # ... and of mean (L d / scale)^2, L the mesh's uniform Laplacian


def fit_steps(settings: FitSettings, n_frames: int, silhouettes: bool = True) -> int:
    """Adam steps :func:`fit_body` takes on ``n_frames`` frames (for a progress bar)."""
    keypoints = settings.global_iterations + settings.iterations
    return keypoints + (settings.silhouette_iterations * len(_passes(settings, n_frames)) if silhouettes else 0)


def _passes(settings: FitSettings, n_frames: int) -> list[tuple[np.ndarray, bool]]:
    """The silhouette stage's passes: (frame indices, whether the shape, offsets and cameras are fitted too). One
    pass over every frame when the take fits in a window; else the spread frames, then the windows (module
    docstring)."""
    size = settings.window
    if size <= 0 or n_frames <= size:
        return [(np.arange(n_frames), True)]
    stride = size - min(settings.window_overlap, size // 2)
    starts = list(range(0, n_frames - size, stride)) + [n_frames - size]
    spread = np.unique(np.linspace(0, n_frames - 1, size).round().astype(int))
    return [(spread, True)] + [(np.arange(a, a + size), False) for a in starts]


@dataclass
class BodyFit:
    """Fitted parameters: poses (F, 72), rh (F, 3), th (F, 3), shapes (10,), offsets (T, 3) metres, and the fitted
    targets (F, T, 3) in the world."""

    poses: np.ndarray
    rh: np.ndarray
    th: np.ndarray
    shapes: np.ndarray
    offsets: np.ndarray
    targets: np.ndarray
    cam_from_world: np.ndarray | None = None  # (V, 3, 4) the corrected cameras, when the fit corrected them
    displacement: np.ndarray | None = None  # (6890,) metres along the template's normals (SMPL+D), when fitted


def fitted_vertices(body: BodyModel, fitted: BodyFit, chunk: int = 100) -> np.ndarray:
    """(F, N, 3) float32 posed vertices of a fit, ``chunk`` frames at a time (the skinning's (chunk, N, 4, 4)
    transforms are the largest thing it holds)."""
    out, offsets = [], body.surface_offsets(fitted.displacement)
    for a in range(0, len(fitted.poses), chunk):
        part = slice(a, a + chunk)
        shapes = np.repeat(fitted.shapes[None], len(fitted.poses[part]), 0)
        args = [
            torch.as_tensor(x, dtype=body.dtype) for x in (fitted.poses[part], fitted.rh[part], fitted.th[part], shapes)
        ]
        with torch.no_grad():
            out.append(body.vertices_zju(*args, template_offsets=offsets).numpy())
    return np.concatenate(out).astype(np.float32)


class SurfacePrior:
    """The displacement's prior, ``a mean u^2 + b mean (u - A u)^2`` of ``u = d / scale`` with A the mean over each
    vertex's mesh neighbours (trimesh's uniform Laplacian): small and smooth, so that a few vertices cannot reach
    for a mask's stray pixels."""

    def __init__(self, body: BodyModel, settings: FitSettings):
        import trimesh
        import trimesh.smoothing

        mesh = trimesh.Trimesh(body.smpl.v_template.numpy(), body.faces, process=False)
        average = trimesh.smoothing.laplacian_calculation(mesh, equal_weight=True).tocoo()
        indices = torch.as_tensor(np.stack([average.row, average.col]), dtype=torch.long)
        weights = torch.as_tensor(average.data, dtype=torch.float32)
        self.average = torch.sparse_coo_tensor(indices, weights, average.shape, check_invariants=True)
        self.settings = settings

    def __call__(self, units: torch.Tensor) -> torch.Tensor:
        s = self.settings
        rough = units - torch.sparse.mm(self.average, units[:, None])[:, 0]
        return s.surface_prior * units.pow(2).mean() + s.surface_smooth * rough.pow(2).mean()


def _kabsch(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising ``|R source + t - target|`` over (N, 3) point pairs."""
    mean_s, mean_t = source.mean(0), target.mean(0)
    u, _, vt = np.linalg.svd((target - mean_t).T @ (source - mean_s))
    fix = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ fix @ vt
    return rotation, mean_t - rotation @ mean_s


def initial_global(rest_targets: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame Rh (rotation vectors) and Th from the torso targets (Kabsch), carried over frames that lack them.

    Args:
        rest_targets: (T, 3) targets of the rest body (SMPL frame). points: (F, T, 3) triangulated, NaN if missing.
    """
    import cv2

    torso = [TARGETS.index(next(t for t in TARGETS if t.name == n)) for n in TORSO_TARGETS]
    rh, th = np.zeros((len(points), 3)), np.full((len(points), 3), np.nan)
    for f, frame in enumerate(points):
        seen = [t for t in torso if np.isfinite(frame[t]).all()]
        if len(seen) < 3:
            continue
        rotation, translation = _kabsch(rest_targets[seen], frame[seen])
        rh[f], th[f] = cv2.Rodrigues(rotation)[0][:, 0], translation
    known = np.flatnonzero(np.isfinite(th[:, 0]))
    if known.size == 0:
        raise ValueError("no frame has three torso joints (hips, shoulders) triangulated: the body cannot be placed")
    nearest = known[np.abs(np.arange(len(points))[:, None] - known[None]).argmin(axis=1)]
    return rh[nearest], th[nearest]


def continuous_rotvecs(rotvecs: np.ndarray) -> np.ndarray:
    """(F, 3) rotation vectors, each replaced by the equivalent ``u (theta + 2 pi k)`` nearest the previous frame's.

    A rotation vector's angle is taken in [0, pi], so a body turning through a half turn jumps from ``~pi u`` to
    ``~-pi u`` between two frames: the fit's smoothness on Rh would then pull those frames through every rotation
    between them. Unwrapped, consecutive vectors differ by the frames' own turn, however often the body turns."""
    out = np.array(rotvecs, np.float64, copy=True)
    for f in range(1, len(out)):
        angle = np.linalg.norm(out[f])
        if angle < 1e-8:
            continue
        axis = out[f] / angle
        turns = np.round((axis @ out[f - 1] - angle) / (2 * np.pi))
        out[f] = axis * (angle + 2 * np.pi * turns)
    return out


class _Problem:
    def __init__(self, body: BodyModel, P, heights, keypoints, points, settings: FitSettings):
        dtype = torch.float32
        self.body, self.settings = body, settings
        self.P = torch.as_tensor(P, dtype=dtype)
        self.heights = torch.as_tensor(heights, dtype=dtype)
        self.xy = torch.as_tensor(np.nan_to_num(keypoints[..., :2]), dtype=dtype)  # (F, V, T, 2)
        weights = np.array([t.weight for t in TARGETS])
        self.conf = torch.as_tensor(keypoints[..., 2] * weights, dtype=dtype)
        self.points = torch.as_tensor(np.nan_to_num(points), dtype=dtype)
        self.seen = torch.as_tensor(np.isfinite(points).all(-1) * weights, dtype=dtype)
        self.joints = list(TARGET_JOINTS)
        sign = np.zeros((len(TARGETS), 3))
        for t, target in enumerate(TARGETS):
            if target.offset:
                mirrored = mirror_index(t) != t
                sign[t] = (-1.0 if target.name.startswith("r_") else 1.0, 1, 1) if mirrored else (0, 1, 1)
        self.offset_sign = torch.as_tensor(sign, dtype=dtype)
        self.offset_source = [mirror_index(t) if TARGETS[t].name.startswith("r_") else t for t in range(len(TARGETS))]
        prior = torch.full((N_JOINTS, 3), settings.pose_prior)
        prior[list(UNOBSERVED_JOINTS)] = settings.unobserved_prior
        self.prior = prior[1:].reshape(-1)

    def subset(self, frames: np.ndarray, settings: FitSettings) -> _Problem:
        """The problem of ``frames`` only (indices), with ``settings``."""
        part = copy.copy(self)
        part.settings = settings
        part.xy, part.conf = self.xy[frames], self.conf[frames]
        part.points, part.seen = self.points[frames], self.seen[frames]
        return part

    def targets(self, poses, rh, th, shapes, offsets) -> torch.Tensor:
        """(F, T, 3) world positions of the targets."""
        rest = self.body.rest_joints(shapes).expand(poses.shape[0], -1, -1)
        world_from_joint = world_from_joints(
            poses.reshape(-1, N_JOINTS, 3), rest, rigid_from_rotvec_translation(rh, th)
        )
        frames = world_from_joint[:, self.joints]  # (F, T, 4, 4)
        local = offsets[self.offset_source] * self.offset_sign
        return frames[..., :3, 3] + (frames[..., :3, :3] @ local[..., None])[..., 0]

    def energy(
        self, poses, rh, th, shapes, offsets, P: torch.Tensor | None = None, before=None, reach: float = 1.0
    ) -> torch.Tensor:
        """The energy of the module docstring; ``P`` (V, 3, 4): the projections to use (corrected cameras);
        ``before``: (poses (1, 72), rh (1, 3), th (1, 3)) of a frame before the first, held, for the smoothness;
        ``reach`` >= 1: the robust kernel ``r^2 / (1 + (r / reach)^2)``, as near zero as Geman-McClure's but
        saturating ``reach`` times further out (module docstring, *Graduated reach*)."""
        s = self.settings
        targets = self.targets(poses, rh, th, shapes, offsets)
        robust = lambda r: r**2 / ((r / reach) ** 2 + 1)  # noqa: E731
        r3 = (targets - self.points).norm(dim=-1) / s.scale_3d
        e3 = (self.seen * robust(r3)).sum() / self.seen.sum().clamp(min=1)
        homogeneous = torch.cat([targets, torch.ones_like(targets[..., :1])], dim=-1)
        image = torch.einsum("vij,ftj->fvti", self.P if P is None else P, homogeneous)
        projected = image[..., :2] / image[..., 2:].clamp(min=1e-3)
        r2 = (projected - self.xy).norm(dim=-1) / (self.heights[None, :, None] * s.scale_2d)
        e2 = (self.conf * robust(r2)).sum() / self.conf.sum().clamp(min=1)
        body = poses[:, 3:]
        prior = (body**2 * self.prior).sum(-1).mean()
        smooth = torch.zeros(())
        chain = (body, rh, th)
        if before is not None:  # the held frame first
            chain = [torch.cat([b, x]) for b, x in zip((before[0][:, 3:], before[1], before[2]), chain)]
        if len(chain[0]) > 1:  # th in metres weighs 10x: 1 cm of jitter costs as much as 0.1 rad
            step = lambda x: ((x[1:] - x[:-1]) ** 2).sum(-1).mean()  # noqa: E731
            smooth = step(chain[0]) + step(chain[1]) + 10 * step(chain[2])
        return (
            s.weight_3d * e3
            + s.weight_2d * e2
            + prior
            + s.smooth * smooth
            + s.shape_prior * (shapes**2).sum()
            + s.offset_prior * (offsets**2).sum()
        )


class CameraCorrection:
    """A correction of every camera's pose, ``cam_from_world' = [exp(r_v) | s_v] cam_from_world`` (a turn about
    the camera's centre, then a shift in its frame), with the prior ``mean_v (|r_v| / a)^2 + (|s_v| / b)^2``, a and b
    the settings' scales: the calibration is trusted to about that much.

    Args:
        K: (V, 3, 3) intrinsics. cam_from_world: (V, 3, 4) extrinsics of the undistorted cameras.
    """

    def __init__(self, K: np.ndarray, cam_from_world: np.ndarray, settings: FitSettings):
        self.K = torch.as_tensor(K, dtype=torch.float32)
        self.extrinsics = torch.as_tensor(cam_from_world[:, :3], dtype=torch.float32)
        self.turn = torch.zeros(len(K), 3, requires_grad=True)
        self.shift = torch.zeros(len(K), 3, requires_grad=True)
        self.scales = (np.radians(settings.camera_turn), settings.camera_shift)

    def corrected(self) -> torch.Tensor:
        """(V, 3, 4) corrected ``cam_from_world``."""
        turn = batch_rodrigues(self.turn)
        return torch.cat([turn @ self.extrinsics[..., :3], turn @ self.extrinsics[..., 3:] + self.shift[..., None]], -1)

    def projections(self) -> torch.Tensor:
        """(V, 3, 4) ``K [R' | t']``."""
        return self.K @ self.corrected()

    def penalty(self) -> torch.Tensor:
        a, b = self.scales
        return ((self.turn / a).pow(2).sum(-1) + (self.shift / b).pow(2).sum(-1)).mean()


def _silhouette_pass(problem, body, silhouettes, frames, every, mask, shared, settings, tick, before=None):
    """One pass of the last stage of :func:`fit_body` over ``frames`` (indices; ``problem`` is theirs): keypoints
    plus ``settings.silhouette_weight`` times the silhouette term built at the keypoint fit's vertices, seen by
    ``problem.P``. ``every``: the fit's (poses, rh, th, shapes, offsets, units), of which the frames' poses, rh and
    th are fitted (from their values) and returned. With ``shared`` (a (K, cam_from_world) pair, or True without
    cameras) the shape, the offsets and the surface's displacement (``units``, in ``settings.surface_scale``; None:
    not fitted) are fitted too, in place, and with cameras and ``settings.refine_cameras`` the cameras' poses
    (:class:`CameraCorrection`, returned; else None). ``before``: the held frame before, for the smoothness."""
    poses, rh, th, shapes, offsets, units = every
    index = torch.as_tensor(frames)
    own = [x[index].detach().clone().requires_grad_() for x in (poses, rh, th)]

    def posed(vertex_step: int = 1):
        args = (own[0] * mask, own[1], own[2], shapes.expand(len(frames), -1))
        offsets = None if units is None else body.surface_offsets(units * settings.surface_scale)
        return body.vertices_zju(*args, vertex_step, template_offsets=offsets)

    with torch.no_grad():
        term = silhouettes(posed().numpy(), frames)
    stride = term.settings.vertex_stride  # the term sees every stride-th vertex: only those are posed
    correction, variables, prior = None, own, None
    if shared is not None:
        variables = [*own, shapes, offsets]
        if units is not None:
            variables, prior = [*variables, units], SurfacePrior(body, settings)
        if shared is not True and settings.refine_cameras:
            correction = CameraCorrection(*shared, settings)
            variables = [*variables, correction.turn, correction.shift]

    def energy():
        P = problem.P if correction is None else correction.projections()
        total = problem.energy(own[0] * mask, own[1], own[2], shapes, offsets, P, before)
        total = total + settings.silhouette_weight * term(posed(stride), P, strided=True)
        total = total if prior is None else total + prior(units)
        return total if correction is None else total + correction.penalty()

    adam_stage(energy, variables, settings.silhouette_iterations, settings.silhouette_lr, tick)
    return [x.detach() for x in own], correction


def _silhouette_stage(problem, body, silhouettes, every, mask, cameras, settings, tick):
    """The last stage of :func:`fit_body`, in the passes of :func:`_passes` (module docstring); ``every``'s
    tensors are updated in place. Returns the :class:`CameraCorrection` or None."""
    poses, rh, th, shapes, offsets, units = every
    passes = _passes(settings, len(poses))
    frames, _ = passes[0]
    alone = len(passes) == 1
    part = problem.subset(frames, settings if alone else replace(settings, smooth=0.0))
    shared = cameras if cameras is not None else True
    fitted, correction = _silhouette_pass(part, body, silhouettes, frames, every, mask, shared, settings, tick)
    if alone:
        _write_back((poses, rh, th), frames, fitted)
        return correction
    if correction is not None:
        problem = copy.copy(problem)
        problem.P = correction.projections().detach()
    held = [poses, rh, th, shapes.detach(), offsets.detach(), None if units is None else units.detach()]
    for frames, _ in passes[1:]:
        a = int(frames[0])
        before = None if a == 0 else [x[a - 1 : a].detach() for x in (poses, rh, th)]
        part = problem.subset(frames, settings)
        fitted, _ = _silhouette_pass(part, body, silhouettes, frames, held, mask, None, settings, tick, before)
        _write_back((poses, rh, th), frames, fitted)
    return correction


def _write_back(tensors, frames: np.ndarray, fitted) -> None:
    """``tensors[i][frames] = fitted[i]``, outside autograd."""
    with torch.no_grad():
        for x, y in zip(tensors, fitted):
            x[torch.as_tensor(frames)] = y


def fit_body(
    body: BodyModel,
    P,
    heights,
    keypoints,
    points,
    settings: FitSettings = FitSettings(),
    progress=None,
    silhouettes=None,
    cameras: tuple[np.ndarray, np.ndarray] | None = None,
    start: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> BodyFit:
    """Fit the body model to a sequence (module docstring).

    Args:
        body: the body model. P: (V, 3, 4) undistorted projections. heights: (V,) image heights (px).
        keypoints: (F, V, T, 3) undistorted target pixels and confidences (0: not used).
        points: (F, T, 3) triangulated targets (NaN: missing).
        progress: optional callable(step, total) for a progress bar.
        silhouettes: optional ``(vertices (n, N, 3) of the keypoint fit, frames (n,) indices) -> term`` of those
            frames: a last stage adds ``weight * term(vertices, P)`` (``pipelines.prepare.body.masks``) to the
            energy, over every frame or window by window (module docstring).
        cameras: (K (V, 3, 3), cam_from_world (V, 3 or 4, 4)) of the undistorted cameras: with ``silhouettes`` and
            ``settings.refine_cameras``, the last stage also corrects the cameras' poses (:class:`CameraCorrection`).
        start: bodies the user brought (poses (F, 72) with poses[:3] zero, rh (F, 3), th (F, 3), shapes (10,)) to start
            from instead of the keypoints' global alignment (``narf-prepare-capture --smpl-params``).
    """
    problem = _Problem(body, P, heights, keypoints, points, settings)
    n_frames = points.shape[0]
    with torch.no_grad():
        rest = body.rest_joints(torch.zeros(1, 10))[0, list(TARGET_JOINTS)].numpy()
    poses0, rh0, th0, shapes0 = start if start is not None else (None, *initial_global(rest, points), None)
    rh0 = continuous_rotvecs(rh0)  # a half turn between two frames is not a jump
    poses = torch.zeros(n_frames, N_JOINTS * 3) if poses0 is None else torch.as_tensor(poses0, dtype=torch.float32)
    poses = poses.clone().requires_grad_()
    rh = torch.as_tensor(rh0, dtype=torch.float32).clone().requires_grad_()
    th = torch.as_tensor(th0, dtype=torch.float32).clone().requires_grad_()
    shapes = torch.zeros(1, 10) if shapes0 is None else torch.as_tensor(shapes0, dtype=torch.float32).reshape(1, 10)
    shapes = shapes.clone().requires_grad_()
    offsets = torch.zeros(len(TARGETS), 3, requires_grad=True)
    mask = torch.ones(N_JOINTS * 3)
    mask[:3] = 0  # poses[:3] stays 0: the global rotation is Rh
    units = torch.zeros(body.n_vertices, requires_grad=True) if settings.surface and silhouettes is not None else None
    every = [poses, rh, th, shapes, offsets, units]
    reach = [1.0]  # the global stage leaves the limbs, still at rest, to saturate
    keypoint_energy = lambda: problem.energy(poses * mask, rh, th, shapes, offsets, reach=reach[0])  # noqa: E731
    total = fit_steps(settings, n_frames, silhouettes is not None)
    done = [0]

    def tick():
        done[0] += 1
        if progress is not None:
            progress(done[0], total)

    adam_stage(keypoint_energy, [rh, th], settings.global_iterations, settings.lr, tick)
    half, reach[0] = max(settings.iterations // 2, 1), settings.robust_reach  # shrinks to 1 over the first half

    def tick_and_shrink():
        reach[0] = max(reach[0] * (1.0 / settings.robust_reach) ** (1.0 / half), 1.0)
        tick()

    adam_stage(keypoint_energy, every[:5], settings.iterations, settings.lr, tick_and_shrink)
    correction = None
    if silhouettes is not None:
        correction = _silhouette_stage(problem, body, silhouettes, every, mask, cameras, settings, tick)
    with torch.no_grad():
        final = poses * mask
        targets = problem.targets(final, rh, th, shapes, offsets)
    return BodyFit(
        poses=final.detach().numpy().astype(np.float32),
        rh=rh.detach().numpy().astype(np.float32),
        th=th.detach().numpy().astype(np.float32),
        shapes=shapes.detach().numpy()[0].astype(np.float32),
        offsets=(offsets[problem.offset_source] * problem.offset_sign).detach().numpy(),
        targets=targets.numpy(),
        cam_from_world=None if correction is None else correction.corrected().detach().double().numpy(),
        displacement=None if units is None else (units * settings.surface_scale).detach().numpy().astype(np.float32),
    )
