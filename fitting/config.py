"""Typed fit configuration, loaded strictly from YAML presets (an unknown key is an error, a value outside its type
or its ``Literal`` choices too) plus ``--set section.key=value`` overrides. The run's kind (``subject``,
``autoencoder``, ``rigid``) is the top-level ``kind``; run state (the process count of a data-parallel fit) is not a
setting and lives in the checkpoint. docs/guides/fitting.md lists the presets."""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, get_args

import yaml

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"


class ConfigError(ValueError):
    """A config file or override is malformed (names the key and the problem)."""


#: A decimal number as text, exponent with or without a dot (``1e-3``, ``2.5E+4``, ``.5``).
NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?")
#: What a run fits: one avatar per capture, the autoencoder across people, or one rigid object (supplement Table B).
RunKindName = Literal["subject", "autoencoder", "rigid"]
ModelName = Literal[
    "narf_d", "narf_d_sigmoid", "narf_h", "narf_p", "p_nerf", "d_narf", "cnn", "rt_nerf", "rt_nerf_no_pose", "rp_nerf"
]
#: The names older run folders used for the kind, in ``data.dataset`` (and ``kind: autoencoder`` in the checkpoint).
LEGACY_KINDS = {"zju": "subject", "thuman": "autoencoder", "rigid": "rigid"}


@dataclass
class DataConfig:
    subject: str = "taichi"  #: subject name or folder (ZJU-MoCap layout)
    data_root: str | None = None  #: data root (default: $NARF_DATA or data/)
    protocol: Literal["narf", "neuralbody"] = "narf"  #: narf (first 90 % frames train) or neuralbody
    ratio: float = 0.5  #: image resize ratio (Neural Body: 0.5)
    mask_source: Literal["cihp", "mask", "union"] = "cihp"  #: the capture's mask folder (docs/formats.md)
    new_params: bool = True  #: new_params/ (pose blend shapes) instead of params/
    white_background: bool = False  #: composite onto white instead of black
    frame_stride: int = 1  #: use every n-th training frame
    #: subject fits: the capture's measured camera colour gains (colour.json; docs/model.md §6) applied to renders for
    #: a camera, in training and evaluation
    camera_gains: bool = True
    box_frames: int = 100  #: training frames used to fit the part boxes
    train_meshes: int = 0  #: autoencoder: meshes that train (0: the set's synthetic.json, else NARF's 3545)
    renders_per_mesh: int = 10  #: autoencoder: train renders per mesh (NARF: 10)


@dataclass
class ModelConfig:
    name: ModelName = "narf_d"  #: the model; its spec (narf.fields.MODEL_SPECS) says which options below it takes
    width: int = 64  #: hidden width H (paper: 256)
    density_act: Literal["leaky_backward", "softplus"] = "leaky_backward"  #: upstream's, or softplus
    temperature: float = 10.0  #: narf_p only: selector softmax temperature tau
    pose_in_color: bool = True  #: p_nerf only: pose into the colour branch (eq. D)
    box_scale_pad: float = 1.1  #: part boxes: h <- scale * h + abs
    box_abs_pad: float = 0.03  #: part boxes: additive padding (body units)
    #: subject fits: each part holds density only within this many metres of the body (inside it too), on a
    #: shell_resolution^3 grid per box (docs/model.md §1, *Body shells*); 0: the whole box, as the paper
    body_shell: float = 0.0
    #: subject fits on a capture whose bodies wear a fitted surface (``body_surface.npy``): the shell's margin there
    #: (metres; the body then follows the person's outline more closely); 0: ``body_shell`` on every capture
    surface_shell: float = 0.0
    shell_resolution: int = 32
    image_size: int = 128  #: cnn only: side of its square bone maps and output images (paper: 128)
    latent_dim: int = 0  #: autoencoder: size of z_s and of z_a (paper 256); 0 for a per-subject fit
    encoder_channels: int = 32  #: autoencoder: image encoder base width c (paper 32: 32..512 channels)
    #: what the colour may depend on (docs/model.md §4, *Colour conditioning*): the view direction's encoded
    #: frequencies (4: gamma_4 as in the paper; 0: no view direction), its random turn in training (degrees per
    #: tangent axis), the chance that a training ray's pose features xi are zeroed, and the frequencies of xi's
    #: encoding that the colour reads (4: gamma_4 as in the paper; 0: none, the colour is the same in every pose)
    view_freqs: int = 4
    view_jitter: float = 0.0
    pose_dropout: float = 0.0
    pose_freqs: int = 4
    #: subject fits: size of a per-frame appearance code that the colour reads (NeRF-W's; 0: none). Evaluation and
    #: new poses use the zero code, the training frames' mean (docs/model.md §4, *Per-frame appearance*)
    appearance_dim: int = 0
    #: subject fits: the colour's pose features xi of frames the fit did not train on (held-back and novel frames,
    #: other recordings, new motions): ``nearest``, those of the trained frame whose pelvis stands nearest in the
    #: world; ``own``, their own (the paper). Models whose density reads xi always use their own (docs/model.md §4,
    #: *Colour of frames not trained on*)
    novel_colour: Literal["nearest", "own"] = "nearest"
    #: narf_d: what each part's density block reads (docs/model.md §2, *Part grids*): ``frequency``, gamma_10 of the
    #: box coordinates (the paper); ``grid``, learned multi-resolution grids in each part's box, ``grid_levels``
    #: levels of ``grid_features`` features from ``grid_min_resolution`` to ``grid_max_resolution`` cells per axis,
    #: 2^``grid_log2_rows`` rows a level and part (finer levels hashed into them)
    encoding: Literal["frequency", "grid"] = "frequency"
    grid_levels: int = 8
    grid_features: int = 2
    grid_min_resolution: int = 8
    grid_max_resolution: int = 128
    grid_log2_rows: int = 12
    #: narf_d: the trunk's residual blocks B, 2 + 2 B layers of ``width`` (the paper: 3); fewer make the small
    #: network on top of the part grids (docs/model.md §2, *Part grids*)
    trunk_blocks: int = 3
    #: narf_d: Lambertian shading, the colour an albedo times a learned world lighting at a predicted normal
    #: (docs/model.md §3, *Shading*; the paper has none): the texture stays put while the body turns under the lights
    shading: bool = False


@dataclass
class RenderConfig:
    train_coarse: int = 16  #: coarse samples per ray in training (paper 48)
    train_fine: int = 16  #: importance samples per ray in training (paper 48)
    eval_coarse: int = 16  #: coarse samples per ray in evaluation (paper 64)
    eval_fine: int = 16  #: importance samples per ray in evaluation (paper 128)
    #: coarse and importance samples per ray of the fit's own validation renders: the held-back frames' score that
    #: chooses the step kept (docs/model.md §7) and the previews in RUN/val/; val_coarse 0: both the evaluation's.
    #: Every step is scored alike, so an estimator cheaper than the final renders' ranks them as well
    val_coarse: int = 0
    val_fine: int = 0
    chunk: int = 1024  #: rays per full-image rendering chunk: bounds memory; 1,024 kept a CPU faster than 4,096 (cache)
    occupancy: bool = False  #: per-subject fits: narrow each ray to its occupied stretch (docs/model.md §5)
    occupancy_resolution: int = 24  #: occupancy cells per axis of each part box
    occupancy_threshold: float = 0.5  #: density below which a cell is empty (per world unit of depth; 1 % over 2 cm)
    occupancy_every: int = 16  #: refresh the grid every n training steps
    occupancy_rounds: int = 4  #: a refresh measures 1/n of the cells, so every cell is measured every n refreshes
    grid_proposal: bool = False  #: training: importance samples follow the grid's density, no coarse field pass

    def validation_samples(self) -> tuple[int, int]:
        """(coarse, fine) samples per ray of the fit's validation renders: ``val_*``, or ``eval_*`` when val_coarse
        is 0."""
        if self.val_coarse == 0:
            return self.eval_coarse, self.eval_fine
        return self.val_coarse, self.val_fine


@dataclass
class TrainConfig:
    steps: int = 20000  #: optimisation steps
    images_per_step: int = 16  #: images per batch (paper 16)
    rays_per_image: int = 64  #: rays per image (paper 576)
    views_per_frame: int = 1  #: >1: each step's images are this many views each of fewer frames (pose correction)
    body_fraction: float = 0.7  #: share of rays on body pixels
    border_fraction: float = 0.2  #: share on a band around the silhouette; the rest on background in the box
    lr: float = 0.01  #: Adam learning rate (equalized-lr layers assume 0.01)
    encoder_lr: float = 0.001  #: autoencoder: Adam learning rate of the image encoder (plain conv layers)
    colour_jitter: float = 0.0  #: autoencoder: per-image channel gains in [1-j, 1+j] on input and target (0: off)
    lr_decay: float = 0.99995  #: multiplicative decay per step (upstream)
    lr_min: float = 0.0  #: floor of the decayed learning rate
    lr_anneal: float = 0.0  #: the last fraction of the budget (steps or minutes) over which the rate falls (0: off)
    lr_anneal_to: float = 0.1  #: with lr_anneal: the rate's multiplier at the end of the budget
    adam_eps: float = 1e-12  #: Adam epsilon (upstream)
    adam_beta2: float = 0.999  #: Adam's decay of the squared gradients' average (upstream 0.999; Instant-NGP 0.99)
    mask_weight: float = 1.0  #: lambda_mask (0: ablation)
    colour_delta: float = 0.0  #: >0: the colour loss is the pseudo-Huber of this scale (docs/model.md §6; 0: squared)
    checkpoint_minutes: float = 3.0  #: write a checkpoint at least this often
    validate_every: int = 1000  #: render a validation image every n steps (0: never)
    log_every: int = 50  #: write a log line every n steps
    seed: int = 0  #: seed of initialisation and ray sampling
    #: fp32 (the reference), bf16 (autocast of the forward pass) or tf32 (CUDA matmuls in TensorFloat-32; on a CPU
    #: the same as fp32)
    precision: Literal["fp32", "bf16", "tf32"] = "fp32"
    compile: bool = False  #: torch.compile the field's forward pass (dynamic shapes; the eager path is the reference)
    deterministic: bool = True  #: deterministic kernels, so a resumed fit ends where an uninterrupted one would
    pose_correction: bool = False  #: subject fits: correct each training frame's body pose while fitting
    pose_lr: float = 2e-3  #: learning rate of the pose corrections' turns (radians; per-knot Adam)
    pose_shift_lr: float = 1e-3  #: learning rate of the pose corrections' shifts (metres)
    pose_start: int = 1000  #: the step from which the poses are corrected (the field takes shape first)
    pose_prior: float = 1e-5  #: weight of the robust pull of each knot's correction towards the capture's pose
    pose_prior_degrees: float = 5.0  #: the prior's scale of a joint's turn (a turn this size costs half of 1)
    pose_prior_cm: float = 3.0  #: the prior's scale of the body's shift
    pose_smooth: float = 0.0  #: pull of neighbouring knots' corrections towards each other (in the prior's units)
    pose_knot_every: int = 1  #: capture frames between pose-correction knots (1: every frame its own)
    pose_gradient_freqs: int = 4  #: encoding frequencies that pass the pose's gradient (10: all; docs/model.md §6)
    mask_body_iterations: int = 150  #: subject fits (NeRF-type): refine the bodies against the masks first (0: off)
    #: with the refinement: refine also bodies that wear the capture's fitted surface (``body_surface.npy``, fitted by
    #: narf-prepare-capture to every camera's masks with the poses); off: those bodies are kept as the capture has them
    refine_surface_bodies: bool = False
    camera_colour: bool = False  #: subject fits: a colour gain and bias per training camera, in the loss only
    colour_lr: float = 1e-3  #: Adam learning rate of the camera colour transforms
    colour_prior: float = 1e-3  #: pull of each camera's transform towards the identity
    random_background: bool = False  #: random background colour per ray; the mask's band leaves the colour loss
    appearance_decay: float = 1e-3  #: with model.appearance_dim: weight decay of the per-frame codes (mean |a_f|^2)
    entropy_weight: float = 0.0  #: weight of the ray entropy on virtual cameras around the body (0: off)
    virtual_rays: int = 256  #: with the entropy: rays of virtual cameras per step
    smoothness_weight: float = 0.0  #: weight of RegNeRF's depth smoothness on virtual patches (0: off)
    virtual_patches: int = 4  #: with the smoothness: 8x8 patches of virtual cameras per step
    mirror_weight: float = 0.0  #: weight of the left-right colour symmetry on virtual rays (0: off)
    mirror_rays: int = 256  #: with the symmetry: virtual rays per step, each rendered with its mirror image
    outline_weight: float = 0.0  #: weight of the bodies' outline seen by virtual cameras (0: off; docs/model.md §6)
    outline_rays: int = 128  #: with the outline: rays of the virtual cameras' outline bands per step
    outline_beside: float = 1.0  #: with the outline: weight of its rays that pass beside the body (0: through it only)
    s3im_weight: float = 0.0  #: weight of the stochastic structural similarity over the training rays (0: off)
    s3im_repeats: int = 10  #: with S3IM: random groupings of the batch's rays per step
    #: with S3IM: "batch", a group takes rays from anywhere in the batch; "camera", from one training camera only
    s3im_groups: Literal["batch", "camera"] = "batch"
    s3im_fade: bool = False  #: with S3IM: its weight falls linearly from train.s3im_weight to 0 over the fit's budget
    holdout_every: int = 0  #: subject fits: every n-th training frame is held back to choose the step kept (0: none)
    select_every: int = 500  #: with a holdout: steps between scores of the held-back frames
    select_rays: int = 4096  #: with a holdout: the person pixels of the held-back frames each score renders
    #: with a holdout: a later step is kept when its score lies within this many paired standard errors of the best
    #: score's (0: the best score alone; fitting.selection)
    select_margin: float = 0.0
    keep: Literal["best", "last"] = "best"  #: with a holdout: evaluate the weights the selection kept or the last
    #: >0: the weights scored, kept and evaluated are their moving average with this decay (docs/model.md §7; 0: off)
    ema_decay: float = 0.0
    window_steps: int = 0  #: coarse-to-fine: steps over which gamma_10's frequencies open (0: all open from the start)
    window_start: float = 4.0  #: coarse-to-fine: the frequencies open at step 0 (docs/model.md §2)
    #: with model.encoding grid (docs/model.md §2, *Part grids*): the grid tables' Adam learning rate (their own:
    #: the network's layers are equalised, the tables are not), their weight decay (added to the gradient, as L2),
    #: and the weight of their smoothness (the squared feature difference across one cell at random points of the
    #: parts' boxes, every level, ``grid_smooth_points`` a step; 0: off)
    grid_lr: float = 0.03
    grid_decay: float = 0.0
    grid_smoothness: float = 0.0
    grid_smooth_points: int = 2048


@dataclass
class FitConfig:
    kind: RunKindName = "subject"  #: what the run fits (``pipelines.runs.kinds``)
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _coerce(path: str, value, hint):
    """``value`` checked against the field's type hint: bool, int, float, str, ``X | None`` or a ``Literal``."""
    if typing.get_origin(hint) is Literal:
        if value not in typing.get_args(hint):
            choices = ", ".join(map(str, typing.get_args(hint)))
            raise ConfigError(f"config key '{path}': expected one of {choices}, got {value!r}")
        return value
    if isinstance(hint, types.UnionType):  # str | None
        if value is None:
            return None
        hint = next(arg for arg in typing.get_args(hint) if arg is not type(None))
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"config key '{path}': expected true/false, got {value!r}")
        return value
    if hint in (int, float):
        if isinstance(value, str) and NUMBER.fullmatch(value.strip()):
            value = float(value)  # YAML 1.1 reads 1e-3 (no dot) as a string; it is the form users type most
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"config key '{path}': expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"config key '{path}': expected a finite number, got {value!r}")
        if hint is int and float(value) != int(value):
            raise ConfigError(f"config key '{path}': expected an integer, got {value!r}")
        return hint(value)
    if hint is str and not isinstance(value, str):
        raise ConfigError(f"config key '{path}': expected a string, got {value!r}")
    return value


def _apply(target, values: dict, prefix: str = "") -> None:
    if not isinstance(values, dict):
        raise ConfigError(f"config section '{prefix or 'top level'}': expected a mapping, got {values!r}")
    hints = typing.get_type_hints(type(target))
    for key, value in values.items():
        path = f"{prefix}{key}"
        if key not in hints:
            raise ConfigError(f"unknown config key '{path}' (known: {', '.join(sorted(hints))})")
        current = getattr(target, key)
        if dataclasses.is_dataclass(current):
            _apply(current, value, path + ".")
        else:
            setattr(target, key, _coerce(path, value, hints[key]))


def migrate_saved(saved: dict, checkpoint_kind: str | None = None) -> dict:
    """A run folder's saved config in today's keys. Older runs named the kind in ``data.dataset`` (zju, thuman,
    rigid; the autoencoder's checkpoint also said ``kind: autoencoder``) and kept the process count in
    ``train.world_size``; both are read here, so every run folder written since loads as it was fitted. A saved
    config without ``train.mask_body_iterations`` predates the refinement of the bodies against the masks: 0; one
    without ``train.pose_gradient_freqs`` corrected its poses through every frequency: 10; one without
    ``train.refine_surface_bodies`` refined bodies that wear the capture's surface too: true."""
    if not isinstance(saved, dict):
        raise ConfigError(f"saved config: expected a mapping, got {type(saved).__name__}")
    saved = {k: dict(v) if isinstance(v, dict) else v for k, v in saved.items()}
    data, train = saved.get("data", {}), saved.get("train", {})
    legacy = data.pop("dataset", None) if isinstance(data, dict) else None
    if isinstance(train, dict):
        train.pop("world_size", None)
        # runs fitted before the bodies were refined against the masks keep their capture's bodies
        train.setdefault("mask_body_iterations", 0)
        # ... and those fitted before the pose's gradient was band-limited passed it through every frequency
        train.setdefault("pose_gradient_freqs", 10)
        # ... and those fitted before the capture's fitted surface kept its bodies refined them as well
        train.setdefault("refine_surface_bodies", True)
    if "kind" not in saved and (legacy is not None or checkpoint_kind is not None):
        name = checkpoint_kind if checkpoint_kind == "autoencoder" else legacy
        if name not in LEGACY_KINDS and name not in LEGACY_KINDS.values():
            raise ConfigError(f"saved config: unknown data.dataset {name!r} (known: {', '.join(LEGACY_KINDS)})")
        saved["kind"] = LEGACY_KINDS.get(name, name)
    return saved


def preset_path(name_or_path: str) -> Path:
    """A preset name (``cpu``, ``paper``, ``tiny``) or a YAML file path."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml"):
        if not path.is_file():
            raise ConfigError(f"{path}: config file not found")
        return path
    candidate = CONFIG_DIR / f"{name_or_path}.yaml"
    if not candidate.is_file():
        known = ", ".join(sorted(p.stem for p in CONFIG_DIR.glob("*.yaml")))
        raise ConfigError(f"unknown preset '{name_or_path}' (presets: {known}; or give a .yaml file)")
    return candidate


def with_eval_samples(config: FitConfig, coarse: int, fine: int) -> FitConfig:
    """``config`` whose renders of a fitted field (``render.eval_coarse`` / ``eval_fine``) take ``coarse`` + ``fine``
    samples a ray; everything else as it was."""
    return dataclasses.replace(config, render=dataclasses.replace(config.render, eval_coarse=coarse, eval_fine=fine))


def load_config(preset: str | None = None, overrides: list[str] | None = None, base: dict | None = None) -> FitConfig:
    """Build a FitConfig from defaults, a base dict (a run's saved config), a preset and ``key=value`` overrides.

    A preset may hold a ``models:`` section, ``{model name: settings}``: the settings of the model the config ends
    up with are applied after the rest of the preset and before the overrides (the autoencoder presets train P-NeRF
    and NARF_H at lr 0.001, as the supplement does)."""
    config = FitConfig()
    if base:
        _apply(config, migrate_saved(base))
    parsed = [_parse_override(item) for item in overrides or []]
    if preset:
        path = preset_path(preset)
        try:
            values = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as err:
            raise ConfigError(f"{path}: not valid YAML ({err})") from err
        try:
            sections = (values.pop("models", None) if isinstance(values, dict) else None) or {}
            _apply(config, values)
            named = [n["model"]["name"] for n in parsed if isinstance(n.get("model"), dict) and "name" in n["model"]]
            model = named[-1] if named else config.model.name
            if not isinstance(sections, dict) or not all(isinstance(v, dict) for v in sections.values()):
                raise ConfigError("models: expected a mapping of model names to settings")
            if set(sections) - set(get_args(ModelName)):
                raise ConfigError(f"models: unknown model(s) {sorted(set(sections) - set(get_args(ModelName)))}")
            _apply(config, sections.get(model) or {})
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}") from err
    for nested in parsed:
        _apply(config, nested)
    validate_config(config)
    return config


def _parse_override(item: str) -> dict:
    """``section.key=value`` as a nested dict, the value read as plain YAML."""
    if "=" not in item:
        raise ConfigError(f"override '{item}': expected section.key=value")
    key, raw = item.split("=", 1)
    parts = key.strip().split(".")
    nested: dict = {}
    cursor = nested
    for part in parts[:-1]:
        cursor = cursor.setdefault(part, {})
    try:
        cursor[parts[-1]] = yaml.safe_load(raw)
    except yaml.YAMLError as err:
        reason = str(err).strip().splitlines()[0]
        raise ConfigError(f"override '{item}': the value is not plain YAML ({reason})") from err
    return nested


#: Settings that only one run kind reads; another kind refuses a value other than the default (rather than ignore it).
KIND_ONLY = {
    "model.latent_dim": "autoencoder",
    "model.encoder_channels": "autoencoder",
    "train.encoder_lr": "autoencoder",
    "train.colour_jitter": "autoencoder",
    "data.train_meshes": "autoencoder",
    "data.renders_per_mesh": "autoencoder",
    "train.pose_correction": "subject",
    "model.body_shell": "subject",
    "model.surface_shell": "subject",
    "model.shell_resolution": "subject",
    "train.camera_colour": "subject",
    "data.camera_gains": "subject",
    "train.random_background": "subject",
    "train.holdout_every": "subject",
    "train.ema_decay": "subject",
    "train.entropy_weight": "subject",
    "train.smoothness_weight": "subject",
    "train.mirror_weight": "subject",
    "train.outline_weight": "subject",
    "train.s3im_weight": "subject",
    "model.appearance_dim": "subject",
    "model.novel_colour": "subject",
    "train.appearance_decay": "subject",
}
#: The range of each numeric setting, as a test and its words (the message names the key, the range and the value).
RANGES = {
    "data.ratio": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "data.frame_stride": (lambda v: v >= 1, ">= 1"),
    "data.box_frames": (lambda v: v >= 1, ">= 1"),
    "data.train_meshes": (lambda v: v >= 0, ">= 0"),
    "data.renders_per_mesh": (lambda v: v >= 1, ">= 1"),
    "model.width": (lambda v: v >= 4, ">= 4"),
    "model.temperature": (lambda v: v > 0, "> 0"),
    "model.box_scale_pad": (lambda v: v > 0, "> 0"),
    "model.box_abs_pad": (lambda v: v >= 0, ">= 0"),
    "model.body_shell": (lambda v: v >= 0, ">= 0 (metres; 0: whole boxes)"),
    "model.surface_shell": (lambda v: v >= 0, ">= 0 (metres; 0: model.body_shell)"),
    "model.shell_resolution": (lambda v: 2 <= v <= 128, "in [2, 128]"),
    "model.image_size": (lambda v: v >= 32 and v % 32 == 0, "a multiple of 32, >= 32"),
    "model.latent_dim": (lambda v: v >= 0, ">= 0"),
    "model.encoder_channels": (lambda v: v >= 1, ">= 1"),
    "model.view_freqs": (lambda v: 0 <= v <= 4, "in [0, 4]"),
    "model.pose_freqs": (lambda v: 0 <= v <= 4, "in [0, 4]"),
    "model.view_jitter": (lambda v: 0 <= v <= 45, "in [0, 45] (degrees)"),
    "model.pose_dropout": (lambda v: 0 <= v < 1, "in [0, 1)"),
    "model.appearance_dim": (lambda v: v >= 0, ">= 0 (0: none)"),
    "render.train_coarse": (lambda v: v >= 2, ">= 2"),
    "render.train_fine": (lambda v: v >= 0, ">= 0"),
    "render.eval_coarse": (lambda v: v >= 2, ">= 2"),
    "render.eval_fine": (lambda v: v >= 0, ">= 0"),
    "render.val_coarse": (lambda v: v == 0 or v >= 2, "0 (the evaluation's) or >= 2"),
    "render.val_fine": (lambda v: v >= 0, ">= 0"),
    "render.chunk": (lambda v: v >= 1, ">= 1"),
    "render.occupancy_resolution": (lambda v: v >= 2, ">= 2"),
    "render.occupancy_threshold": (lambda v: v >= 0, ">= 0"),
    "render.occupancy_every": (lambda v: v >= 1, ">= 1"),
    "render.occupancy_rounds": (lambda v: v >= 1, ">= 1"),
    "train.steps": (lambda v: v >= 0, ">= 0"),
    "train.images_per_step": (lambda v: v >= 1, ">= 1"),
    "train.rays_per_image": (lambda v: v >= 1, ">= 1"),
    "train.views_per_frame": (lambda v: v >= 1, ">= 1"),
    "train.body_fraction": (lambda v: 0 <= v <= 1, "in [0, 1]"),
    "train.border_fraction": (lambda v: 0 <= v <= 1, "in [0, 1]"),
    "train.lr": (lambda v: v > 0, "> 0"),
    "train.encoder_lr": (lambda v: v > 0, "> 0"),
    "train.colour_jitter": (lambda v: 0 <= v < 1, "in [0, 1)"),
    "train.lr_decay": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "train.lr_min": (lambda v: v >= 0, ">= 0"),
    "train.lr_anneal": (lambda v: 0 <= v <= 1, "in [0, 1]"),
    "train.lr_anneal_to": (lambda v: 0 < v <= 1, "in (0, 1]"),
    "train.adam_eps": (lambda v: v > 0, "> 0"),
    "train.adam_beta2": (lambda v: 0 < v < 1, "in (0, 1)"),
    "train.mask_weight": (lambda v: v >= 0, ">= 0"),
    "train.colour_delta": (lambda v: v >= 0, ">= 0 (0: the squared error)"),
    "train.checkpoint_minutes": (lambda v: v >= 0, ">= 0 (0: after every step)"),
    "train.validate_every": (lambda v: v >= 0, ">= 0 (0: never)"),
    "train.log_every": (lambda v: v >= 1, ">= 1"),
    "train.pose_lr": (lambda v: v > 0, "> 0"),
    "train.pose_start": (lambda v: v >= 0, ">= 0"),
    "train.pose_prior": (lambda v: v >= 0, ">= 0"),
    "train.pose_shift_lr": (lambda v: v > 0, "> 0"),
    "train.pose_prior_degrees": (lambda v: v > 0, "> 0"),
    "train.pose_prior_cm": (lambda v: v > 0, "> 0"),
    "train.pose_smooth": (lambda v: v >= 0, ">= 0"),
    "train.pose_knot_every": (lambda v: v >= 1, ">= 1"),
    "train.pose_gradient_freqs": (lambda v: 1 <= v <= 10, "in [1, 10]"),
    "train.mask_body_iterations": (lambda v: v >= 0, ">= 0"),
    "train.colour_lr": (lambda v: v > 0, "> 0"),
    "train.colour_prior": (lambda v: v >= 0, ">= 0"),
    "train.appearance_decay": (lambda v: v >= 0, ">= 0"),
    "train.entropy_weight": (lambda v: v >= 0, ">= 0 (0: off)"),
    "train.virtual_rays": (lambda v: v >= 1, ">= 1"),
    "train.mirror_weight": (lambda v: v >= 0, ">= 0 (0: off)"),
    "train.mirror_rays": (lambda v: v >= 1, ">= 1"),
    "train.outline_weight": (lambda v: v >= 0, ">= 0 (0: off)"),
    "train.outline_rays": (lambda v: v >= 1, ">= 1"),
    "train.outline_beside": (lambda v: 0 <= v <= 1, "in [0, 1]"),
    "train.s3im_weight": (lambda v: v >= 0, ">= 0 (0: off)"),
    "train.s3im_repeats": (lambda v: v >= 1, ">= 1"),
    "train.smoothness_weight": (lambda v: v >= 0, ">= 0 (0: off)"),
    "train.virtual_patches": (lambda v: v >= 1, ">= 1"),
    "train.holdout_every": (lambda v: v == 0 or v >= 2, "0 (none) or >= 2"),
    "train.select_every": (lambda v: v >= 1, ">= 1"),
    "train.select_margin": (lambda v: v >= 0, ">= 0"),
    "train.select_rays": (lambda v: v >= 1, ">= 1"),
    "train.ema_decay": (lambda v: 0 <= v < 1, "in [0, 1) (0: off)"),
    "train.window_steps": (lambda v: v >= 0, ">= 0 (0: off)"),
    "train.window_start": (lambda v: 0 <= v <= 10, "in [0, 10]"),
    "train.grid_lr": (lambda v: v > 0, "> 0"),
    "train.grid_decay": (lambda v: v >= 0, ">= 0 (0: off)"),
    "train.grid_smoothness": (lambda v: v >= 0, ">= 0 (0: off)"),
    "train.grid_smooth_points": (lambda v: v >= 1, ">= 1"),
    "model.grid_levels": (lambda v: 1 <= v <= 32, "in [1, 32]"),
    "model.grid_features": (lambda v: 1 <= v <= 16, "in [1, 16]"),
    "model.grid_min_resolution": (lambda v: 1 <= v <= 4096, "in [1, 4096]"),
    "model.grid_max_resolution": (lambda v: 1 <= v <= 4096, "in [1, 4096]"),
    "model.grid_log2_rows": (lambda v: 4 <= v <= 24, "in [4, 24]"),
    "model.trunk_blocks": (lambda v: 0 <= v <= 8, "in [0, 8]"),
}


def get_value(config: FitConfig, key: str):
    section, name = key.split(".")
    return getattr(getattr(config, section), name)


def validate_config(config: FitConfig) -> None:
    """Value checks with messages naming the key: ranges, the model's kind, settings of another kind or model."""
    from narf.encodings import POSE_FREQS
    from narf.fields import MODEL_SPECS, model_names

    rigid = config.kind == "rigid"
    allowed = model_names("rigid") if rigid else model_names("field", "image")
    if config.model.name not in allowed:
        kind = "a rigid-object model" if rigid else "a body model"
        raise ConfigError(f"model.name: '{config.model.name}' is not {kind} ({', '.join(allowed)})")
    for key, (ok, words) in RANGES.items():
        if not ok(get_value(config, key)):
            raise ConfigError(f"config key '{key}': must be {words}, got {get_value(config, key)!r}")
    if config.train.lr_min > config.train.lr:
        raise ConfigError(
            f"config key 'train.lr_min': must be <= train.lr ({config.train.lr}), got {config.train.lr_min}"
        )
    if config.train.body_fraction + config.train.border_fraction > 1:
        raise ConfigError("train.body_fraction + train.border_fraction: the shares of body and border rays exceed 1")
    if config.render.val_coarse == 0 and config.render.val_fine:
        raise ConfigError("render.val_fine: set render.val_coarse too (val_coarse 0 takes both of the evaluation's)")
    defaults = FitConfig()
    for key, kind in KIND_ONLY.items():
        if config.kind != kind and get_value(config, key) != get_value(defaults, key):
            raise ConfigError(f"{key}: only {kind} runs use it (this is a {config.kind} run); leave it at its default")
    spec = MODEL_SPECS[config.model.name]
    if config.model.grid_max_resolution < config.model.grid_min_resolution:
        raise ConfigError(
            f"model.grid_max_resolution: must be >= model.grid_min_resolution ({config.model.grid_min_resolution}), "
            f"got {config.model.grid_max_resolution}"
        )
    for option in (
        "temperature",
        "pose_in_color",
        "image_size",
        "appearance_dim",
        "encoding",
        "trunk_blocks",
        "shading",
    ):
        if option not in spec.options and getattr(config.model, option) != getattr(defaults.model, option):
            users = ", ".join(name for name, other in MODEL_SPECS.items() if option in other.options)
            raise ConfigError(f"model.{option}: {config.model.name} does not take it (only {users})")
    autoencoder = config.kind == "autoencoder"
    if autoencoder and config.model.latent_dim == 0:
        raise ConfigError("model.latent_dim: an autoencoder run needs a latent size (paper 256)")
    if config.render.grid_proposal and not config.render.occupancy:
        raise ConfigError("render.grid_proposal: the proposal is the occupancy grid's density; set render.occupancy")
    if config.render.occupancy and autoencoder:  # (image-space models have no rays: the switch does not apply)
        raise ConfigError("render.occupancy: the occupancy grid is for per-subject fits (densities differ per person)")
    if config.train.colour_jitter and not spec.rays:
        raise ConfigError("train.colour_jitter: only the NeRF-type autoencoders use it")
    if spec.pose_in_density:  # the colour's pose settings would reach the geometry
        for key, plain in (("pose_dropout", 0), ("pose_freqs", POSE_FREQS)):
            if getattr(config.model, key) != plain:
                raise ConfigError(
                    f"model.{key}: {config.model.name}'s density reads the pose features; leave it at {plain}"
                )
    if config.model.body_shell and not spec.rays:
        raise ConfigError("model.body_shell: the CNN baseline has no part boxes; leave it at 0")
    if config.model.surface_shell and not config.model.body_shell:
        raise ConfigError("model.surface_shell: shells are off (model.body_shell is 0); set both or neither")
    rays_only = ("pose_correction", "camera_colour", "random_background", "holdout_every", "entropy_weight")
    for key in (*rays_only, "smoothness_weight", "mirror_weight", "outline_weight", "s3im_weight"):
        if getattr(config.train, key) and not spec.rays:
            raise ConfigError(f"train.{key}: the CNN baseline renders no rays; set it false (--set train.{key}=false)")
