"""What a subject fit corrects in its inputs while it fits (docs/model.md §6, *Input corrections*): the body pose of
every training frame (:class:`PoseCorrection`), the colour of every training camera (:class:`CameraColour`), and
the look of every training frame (:class:`FrameAppearance`, docs/model.md §4).

Each starts at zero correction, is pulled back towards it by a penalty, and has its own learning rate; the
trainer adds their parameters to its optimiser and their penalties to its loss (``fitting.trainer``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from smplx.lbs import batch_rodrigues
from torch import nn

from narf.fields.common import PoseBatch
from narf.geometry import check_shape, so3_log
from narf.kinematics import N_JOINTS, part_pose_features, parts_from_joints, world_from_joint_rotations


@dataclass(frozen=True)
class PosePrior:
    """The pose correction's prior (:meth:`PoseCorrection.penalty`): ``weight`` of the robust pull towards the
    capture's pose, at ``turn_degrees`` per joint turn and ``shift_cm`` of the body's shift; ``smooth`` the weight of
    the pull of neighbouring knots together (in the same units)."""

    weight: float = 1e-5  # as train.pose_prior (fitting.config)
    turn_degrees: float = 5.0
    shift_cm: float = 3.0
    smooth: float = 0.0


@dataclass
class CapturePoses:
    """The capture's body parameters of the F training frames, which pose correction starts from.

    Attributes:
        rotvecs: (F, 24, 3) local axis-angle rotations (SMPL ``poses`` reshaped).
        world_from_smpl: (F, 4, 4) the global transform ``[R(Rh) | Th]`` (docs/formats.md §1.6).
        rest_joints: (F, 24, 3) the shaped rest joints in the SMPL frame.
        frames: (F,) capture frame index of each training frame (neighbours in time are smoothed together).
    """

    rotvecs: torch.Tensor
    world_from_smpl: torch.Tensor
    rest_joints: torch.Tensor
    frames: torch.Tensor

    def __post_init__(self):
        check_shape("rotvecs", self.rotvecs, (-1, N_JOINTS, 3))
        n_frames = self.rotvecs.shape[0]
        check_shape("world_from_smpl", self.world_from_smpl, (n_frames, 4, 4))
        check_shape("rest_joints", self.rest_joints, (n_frames, N_JOINTS, 3))
        check_shape("frames", self.frames, (n_frames,))


def knots(frames: torch.Tensor, every: int) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Where each training frame lies among correction knots placed every ``every`` capture frames from the first
    training frame: (left knot (F,), weight of the right knot (F,), number of knots). ``every`` 1: a knot per frame.
    The last knot is the last frame's (or the one after it, when that frame falls between knots)."""
    position = (frames - frames.min()).double() / every
    n_knots = int(position.max().ceil()) + 1
    left = position.floor().long().clamp(max=max(n_knots - 2, 0))
    return left, (position - left).to(torch.get_default_dtype()), n_knots


def _right(left: torch.Tensor, n_knots: int) -> torch.Tensor:
    """The right knot of each frame (its left one for a frame on the last knot, whose weight is then 1 or 0)."""
    return (left + 1).clamp(max=n_knots - 1)


def robust(r2: torch.Tensor) -> torch.Tensor:
    """Geman-McClure of a squared residual, ``r^2 / (r^2 + 1)``: quadratic below 1, bounded by 1 beyond (a large
    correction costs at most 1, so the prior holds the poses the images do not see and lets through those they do).
    Taking r^2 keeps its gradient finite at r = 0."""
    return r2 / (r2 + 1)


class PoseCorrection(nn.Module):
    """Per-frame corrections of the capture's body poses (docs/model.md §6).

    Frame f's joints j >= 1 turn by ``R_j' = R_j exp(delta_fj)`` (in the parent's frame, as SMPL's local rotations),
    and its whole body turns by ``exp(omega_f)`` about its pelvis p_f and moves by ``tau_f``:
    ``world_from_smpl' = [exp(omega_f) | p_f + tau_f - exp(omega_f) p_f] world_from_smpl``. All start at zero.
    The corrections are interpolated linearly in time between knots every ``knot_every`` capture frames (1: each
    training frame has its own), so that a knot gathers the rays of the frames around it.

    Args:
        capture: the training frames' parameters (:class:`CapturePoses`); kept as buffers, so the checkpoint holds
            what the corrections apply to.
        knot_every: capture frames between knots.
        centred: the corrections' mean over the knots is held at zero (:meth:`centre`, after each optimiser
            step). A correction shared by every frame (a joint turned, the body moved, the same in all frames) is
            the field's to learn: its parts can turn or move inside their own frames and render the same images, so
            nothing in the images fixes the mean, and without this it drifts with the optimiser's noise. The mean
            is taken out of the parameters, not of the values the frames use: subtracting it inside the forward pass
            would hand every step's gradient to every knot, and Adam would turn that shared sliver into a full step
            of each knot that no ray saw.
    """

    def __init__(self, capture: CapturePoses, knot_every: int = 1, centred: bool = True):
        super().__init__()
        self.centred = centred
        self.register_buffer("rotvecs", capture.rotvecs.clone())
        self.register_buffer("world_from_smpl", capture.world_from_smpl.clone())
        self.register_buffer("rest_joints", capture.rest_joints.clone())
        self.register_buffer("frames", capture.frames.clone())
        left, weight, n_knots = knots(capture.frames, knot_every)
        self.register_buffer("knot_left", left)
        self.register_buffer("knot_right", _right(left, n_knots))
        self.register_buffer("knot_weight", weight.to(capture.rotvecs.dtype))
        dtype = capture.rotvecs.dtype
        self.joints = nn.Parameter(torch.zeros(n_knots, N_JOINTS - 1, 3, dtype=dtype))
        self.root = nn.Parameter(torch.zeros(n_knots, 3, dtype=dtype))
        self.shift = nn.Parameter(torch.zeros(n_knots, 3, dtype=dtype))

    def knot_values(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The knots' corrections: joint turns (K, 23, 3), root turns (K, 3), shifts (K, 3)."""
        return self.joints, self.root, self.shift

    @torch.no_grad()
    def centre(self) -> None:
        """With ``centred``, take the corrections' mean over the knots out of the parameters (after a step)."""
        if self.centred:
            for value in self.knot_values():
                value.sub_(value.mean(dim=0))

    def values(self, index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The corrections (joint turns (n, 23, 3), root turn (n, 3), shift (n, 3)) of training frames ``index``."""
        left, right, weight = self.knot_left[index], self.knot_right[index], self.knot_weight[index]

        def blend(knot_values: torch.Tensor) -> torch.Tensor:
            w = weight.reshape(-1, *(1,) * (knot_values.dim() - 1))
            return (1 - w) * knot_values[left] + w * knot_values[right]

        return tuple(blend(v) for v in self.knot_values())

    def _pelvis(self, index: torch.Tensor) -> torch.Tensor:
        """(n, 3) world position of the pelvis before correction, ``world_from_smpl J_0``."""
        world = self.world_from_smpl[index]
        return (world[:, :3, :3] @ self.rest_joints[index, 0, :, None])[..., 0] + world[:, :3, 3]

    def _corrected(self, index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Corrected local rotations ``R_j exp(delta_j)`` (n, 24, 3, 3) (joint 0 unchanged) and ``world_from_smpl``
        (n, 4, 4) of training frames ``index`` (n,)."""
        joints, root, shift = self.values(index)
        n = index.numel()
        base = batch_rodrigues(self.rotvecs[index].reshape(-1, 3)).reshape(n, N_JOINTS, 3, 3)
        delta = batch_rodrigues(joints.reshape(-1, 3)).reshape(n, N_JOINTS - 1, 3, 3)
        turn = batch_rodrigues(root)
        pelvis = self._pelvis(index)
        fix = torch.eye(4, dtype=turn.dtype, device=turn.device).repeat(n, 1, 1)
        fix[:, :3, :3] = turn
        fix[:, :3, 3] = pelvis + shift - (turn @ pelvis[..., None])[..., 0]
        return torch.cat([base[:, :1], base[:, 1:] @ delta], dim=1), fix @ self.world_from_smpl[index]

    def world_from_joint(self, index: torch.Tensor) -> torch.Tensor:
        """(n, 24, 4, 4) corrected joint frames of training frames ``index``."""
        local, world_from_smpl = self._corrected(index)
        return world_from_joint_rotations(local, self.rest_joints[index], world_from_smpl)

    def pose_batch(self, index: torch.Tensor, base: PoseBatch) -> PoseBatch:
        """The field's inputs for training frames ``index`` (n,), corrected: ``base`` (the capture's PoseBatch of all
        training frames) with new part transforms and joint frames. Bone lengths, reach and rest offsets do not
        depend on the pose. The pose features xi follow the corrected pose but pass no gradient back to it: the
        correction is driven by where the body is, not by what colour its pose gives it."""
        world_from_joint = self.world_from_joint(index)
        world_from_part = parts_from_joints(world_from_joint)
        selected = base.select(index)
        features = part_pose_features(world_from_part.detach(), selected.reach)
        return replace(
            selected, world_from_part=world_from_part, pose_features=features, world_from_joint=world_from_joint
        )

    def penalty(self, prior: PosePrior, index: torch.Tensor | None = None) -> torch.Tensor:
        """The pull of the knots that training frames ``index`` (all when None) rest on (docs/model.md §6):

        ``w_p mean_k [sum_j rho(|delta_kj| / s_turn) + rho(|omega_k| / s_turn) + rho(|tau_k| / s_shift)]
        + w_s mean_k |(c_(k+1) - c_k) / s|^2``

        with rho :func:`robust`, c_k a knot's corrections in units of the scales (turns in degrees, shifts in cm) and
        the smoothness over neighbouring knots of which one is drawn. A knot enters only where one of the frames
        has weight on it, so no knot is pulled in a step whose rays do not see it."""
        turns = torch.cat([self.joints, self.root[:, None]], dim=1) / math.radians(prior.turn_degrees)
        shifts = self.shift / (prior.shift_cm / 100)
        cost = robust(turns.pow(2).sum(dim=-1)).sum(dim=1) + robust(shifts.pow(2).sum(dim=-1))  # (K,)
        every = slice(None) if index is None else index
        left, right, weight = self.knot_left[every], self.knot_right[every], self.knot_weight[every]
        chosen = torch.zeros(cost.shape[0], dtype=torch.bool, device=cost.device)
        chosen[left[weight < 1]] = True
        chosen[right[weight > 0]] = True
        term = prior.weight * cost[chosen].mean()
        starts = torch.nonzero(chosen[:-1] | chosen[1:])[:, 0]
        if prior.smooth and starts.numel():
            scaled = torch.cat([turns.flatten(1), shifts], dim=1)
            term = term + prior.smooth * (scaled[starts + 1] - scaled[starts]).pow(2).sum(dim=1).mean()
        return term

    @torch.no_grad()
    def zju_params(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The corrected poses in the ZJU-MoCap convention (docs/formats.md §1.6): poses (F, 72), Rh (F, 3),
        Th (F, 3), so that ``R(Rh) SMPL(poses) + Th`` is the corrected body."""
        index = torch.arange(self.rotvecs.shape[0], device=self.rotvecs.device)
        local, world = self._corrected(index)
        poses = torch.cat([self.rotvecs[:, :1], so3_log(local[:, 1:])], dim=1).reshape(-1, 72)
        return poses, so3_log(world[:, :3, :3]), world[:, :3, 3].clone()

    @torch.no_grad()
    def magnitude(self) -> dict[str, float]:
        """Largest and mean correction of the training frames: joint and root turns in degrees, shift in
        centimetres (for logs)."""
        joints, root, shift = self.values(torch.arange(self.frames.numel(), device=self.frames.device))
        turns = torch.cat([joints.reshape(-1, 3), root], dim=0).norm(dim=-1).rad2deg()
        shifts = shift.norm(dim=-1) * 100
        return {
            "pose_turn_max_deg": float(turns.max()),
            "pose_turn_mean_deg": float(turns.mean()),
            "pose_shift_max_cm": float(shifts.max()),
            "pose_shift_mean_cm": float(shifts.mean()),
        }


class CameraColour(nn.Module):
    """A colour transform per training camera, applied to the rendered colour in the training loss only
    (docs/model.md §6): ``C' = g_c * C + M b_c`` per channel, with C the colour on black, M the opacity,
    ``g_c = exp(l_c - mean_k l_k)`` and ``b_c = d_c - mean_k d_k``. The mean transform over the cameras is the
    identity, so the field learns the cameras' common colour, which held-out cameras, videos and meshes show.

    Args:
        n_cameras: training cameras (indices 0..n-1 in the ray batch's ``cameras``).
    """

    def __init__(self, n_cameras: int):
        super().__init__()
        self.log_gain = nn.Parameter(torch.zeros(n_cameras, 3))
        self.offset = nn.Parameter(torch.zeros(n_cameras, 3))

    def transforms(self) -> tuple[torch.Tensor, torch.Tensor]:
        """gains (C, 3) and biases (C, 3) with the mean transform at identity."""
        gains = torch.exp(self.log_gain - self.log_gain.mean(dim=0))
        return gains, self.offset - self.offset.mean(dim=0)

    def forward(self, rgb_on_black: torch.Tensor, opacity: torch.Tensor, cameras: torch.Tensor) -> torch.Tensor:
        """rgb_on_black (R, 3) = sum w c, opacity (R,), cameras (R,) -> the colour camera c would record (R, 3)."""
        gains, biases = self.transforms()
        return gains[cameras] * rgb_on_black + opacity[:, None] * biases[cameras]

    def penalty(self, weight: float) -> torch.Tensor:
        """``weight mean_c (|log g_c|^2 + |b_c|^2)``: a pull towards the identity."""
        gains, biases = self.transforms()
        return weight * (gains.log().pow(2).sum(dim=1) + biases.pow(2).sum(dim=1)).mean()


def camera_response(rgb: torch.Tensor, opacity: torch.Tensor, gains: torch.Tensor, background: float) -> torch.Tensor:
    """What a camera of colour gains ``gains`` records of a render (docs/model.md §6, *Measured camera colour*):
    ``C' = g (C - (1 - M) bg) + (1 - M) bg``, the gain on the person's light only, not on the background the render
    was composited on.

    Args:
        rgb: (..., 3) rendered colour on ``background``. opacity: (...) M. gains: (3,) or broadcastable to ``rgb``.
    """
    behind = (1 - opacity)[..., None] * background
    return gains * (rgb - behind) + behind


class MeasuredColour(nn.Module):
    """The training cameras' measured gains (``colour.json``), fixed, applied to the rendered colour of each ray's
    camera in the training loss, optionally followed by a learned :class:`CameraColour`.

    Args:
        gains: (C, 3) gain of each training camera (indices 0..C-1 of the ray batch's ``cameras``).
        learned: a CameraColour applied after the gains, or None.
    """

    def __init__(self, gains: torch.Tensor, learned: CameraColour | None = None):
        super().__init__()
        self.register_buffer("gains", torch.as_tensor(gains, dtype=torch.float32), persistent=False)
        self.learned = learned

    def forward(self, rgb_on_black: torch.Tensor, opacity: torch.Tensor, cameras: torch.Tensor) -> torch.Tensor:
        """rgb_on_black (R, 3), opacity (R,), cameras (R,) -> the colour camera c records (R, 3)."""
        rgb = self.gains[cameras] * rgb_on_black
        return rgb if self.learned is None else self.learned(rgb, opacity, cameras)


class FrameAppearance(nn.Module):
    """NeRF-W's appearance embedding (Martin-Brualla et al., CVPR 2021), one code per training frame, read by the
    colour branch in the place of the autoencoder's z_a (docs/model.md §4, *Per-frame appearance*). The codes are
    centred, ``a_f = e_f - mean_k e_k``, so the zero code that evaluation and new poses use is the training frames'
    mean look; the weight decay keeps each frame's share small.

    Args:
        n_frames: F training frames (indices 0..F-1 of the training PoseBatch). dim: A, the code size.
    """

    def __init__(self, n_frames: int, dim: int):
        super().__init__()
        self.codes = nn.Parameter(torch.zeros(n_frames, dim))

    def forward(self, frames: torch.Tensor | None = None) -> torch.Tensor:
        """The centred codes of training frames ``frames`` (K,) long, or of every frame: (K or F, A)."""
        centred = self.codes - self.codes.mean(dim=0)
        return centred if frames is None else centred[frames]

    def penalty(self, weight: float) -> torch.Tensor:
        """``weight mean_f |a_f|^2``: the weight decay towards the mean look."""
        return weight * self().pow(2).sum(dim=1).mean()

    def attach(self, poses: PoseBatch, frames: torch.Tensor | None = None) -> PoseBatch:
        """``poses`` (of training frames ``frames``, or of every training frame) with their codes."""
        return replace(poses, appearance=self(frames))


def pose_correction_from_state(state: dict) -> PoseCorrection | None:
    """The pose correction a checkpoint holds (None for a fit without one); its knots are the saved ones. A checkpoint
    of an earlier version, whose centring subtracted the mean inside the forward pass and whose knots had no
    ``knot_right``, gives the same corrections: its parameters are centred here and its right knots derived."""
    saved = state.get("pose_correction")
    if saved is None:
        return None
    saved = dict(saved)
    capture = CapturePoses(*(saved[k] for k in ("rotvecs", "world_from_smpl", "rest_joints", "frames")))
    module = PoseCorrection(capture)
    for name in ("joints", "root", "shift"):  # sized by the saved knots, whatever knot_every made them
        setattr(module, name, nn.Parameter(torch.zeros_like(saved[name])))
    if "knot_right" not in saved:
        saved["knot_right"] = _right(saved["knot_left"], saved["joints"].shape[0])
        saved.update({name: saved[name] - saved[name].mean(dim=0) for name in ("joints", "root", "shift")})
    module.load_state_dict(saved)
    return module


class RowAdam(torch.optim.Optimizer):
    """Adam whose every parameter row (``p[k]``: one knot's corrections) keeps moments and a step count of its own
    and moves only in the steps that give it a gradient, as ``torch.optim.SparseAdam`` does for embeddings.

    A training frame is drawn once in tens of steps. Plain Adam would go on moving its knot on momentum in the steps
    between, each visit's noise turned into a full step in that visit's direction; here a row's first moment
    averages over its own last visits (about 1 / (1 - beta1) of them), so noise cancels and a steady pull adds up.
    Rows whose gradient is exactly zero in a step (no ray of the step saw them) are left as they are."""

    def __init__(self, params, lr: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-12):
        super().__init__(params, {"lr": lr, "betas": betas, "eps": eps})

    @torch.no_grad()
    def step(self, closure=None):
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                grad = p.grad.reshape(p.shape[0], -1)
                rows = grad.ne(0).any(dim=1)
                if not rows.any():
                    continue
                state = self.state[p]
                if not state:
                    state["step"] = torch.zeros(p.shape[0], dtype=torch.float64, device=p.device)
                    state["exp_avg"] = torch.zeros_like(grad)
                    state["exp_avg_sq"] = torch.zeros_like(grad)
                count = state["step"][rows] + 1
                state["step"][rows] = count
                m = state["exp_avg"][rows].mul_(beta1).add_(grad[rows], alpha=1 - beta1)
                v = state["exp_avg_sq"][rows].mul_(beta2).addcmul_(grad[rows], grad[rows], value=1 - beta2)
                state["exp_avg"][rows], state["exp_avg_sq"][rows] = m, v
                m_hat = m / (1 - beta1**count)[:, None].to(m.dtype)
                v_hat = v / (1 - beta2**count)[:, None].to(v.dtype)
                update = group["lr"] * m_hat / (v_hat.sqrt() + group["eps"])
                p.reshape(p.shape[0], -1)[rows] -= update
        return None


def composited_colour(out, batch, background: float | torch.Tensor, camera_colour=None) -> torch.Tensor:
    """(R, 3) C = T_c(sum w c) + (1 - M) bg: ``out`` rendered over black, ``camera_colour`` (T_c, a
    :class:`CameraColour`, or None) applied per ray's camera ``batch.cameras``, composited over ``background`` (a
    value, or (R, 3) one colour per ray)."""
    rgb = out.rgb if camera_colour is None else camera_colour(out.rgb, out.mask, batch.cameras)
    return rgb + (1 - out.mask)[:, None] * background


def background_target(batch, backgrounds: torch.Tensor) -> torch.Tensor:
    """(R, 3) the colour targets under random ``backgrounds`` (R, 3): the recording's colour inside the mask, the ray's
    background colour outside it (docs/model.md §6, *Random background*)."""
    return torch.where(batch.mask[:, None] > 0.5, batch.rgb, backgrounds)


def corrected_colour_error(
    out, batch, background, camera_colour, backgrounds, colour_count, mask_count, penalty=torch.square
):
    """The colour term of ``fitting.losses.ray_loss`` with a camera colour transform (:class:`CameraColour`) and / or
    random backgrounds (R, 3): ``out`` was rendered on black, so C = T_c(sum w c) + (1 - M) bg, against the mask's
    colour inside it and bg outside; the band's rays leave the term when the backgrounds are random.
    ``colour_count`` / ``mask_count``: the normalisers of ``ray_loss``; ``penalty``: of each channel's residual."""
    if backgrounds is None:
        return penalty(composited_colour(out, batch, background, camera_colour) - batch.rgb).sum() / colour_count
    target = background_target(batch, backgrounds)
    error = penalty(composited_colour(out, batch, backgrounds, camera_colour) - target).sum(dim=-1)
    return (batch.mask_weight * error).sum() / (3 * mask_count)
