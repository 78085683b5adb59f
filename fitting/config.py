"""Typed fit configuration, loaded strictly from YAML presets (an unknown key is an error) plus
``--set section.key=value`` overrides."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import yaml

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"


class ConfigError(ValueError):
    """A config file or override is malformed (names the key and the problem)."""


@dataclass
class DataConfig:
    dataset: str = "zju"  #: zju (one subject), thuman (autoencoder across people, render_128) or rigid (one object)
    subject: str = "taichi"  #: subject name or folder (ZJU-MoCap layout)
    data_root: str | None = None  #: data root (default: $NARF_DATA or data/)
    protocol: str = "narf"  #: narf (first 90 % frames train) or neuralbody
    ratio: float = 0.5  #: image resize ratio (Neural Body: 0.5)
    mask_source: str = "cihp"  #: cihp, mask or union
    new_params: bool = True  #: new_params/ (pose blend shapes) instead of params/
    white_background: bool = False  #: composite onto white instead of black
    frame_stride: int = 1  #: use every n-th training frame
    box_frames: int = 100  #: training frames used to fit the part boxes
    train_meshes: int = 0  #: thuman: meshes that train (0: the set's synthetic.json, else NARF's 3545)
    renders_per_mesh: int = 10  #: thuman: train renders per mesh (NARF: 10)


@dataclass
class ModelConfig:
    name: str = "narf_d"  #: narf_d, narf_d_sigmoid, narf_h, narf_p, p_nerf, d_narf, or cnn (the CNN baseline)
    width: int = 64  #: hidden width H (paper: 256)
    density_act: str = "leaky_backward"  #: leaky_backward (upstream) or softplus
    temperature: float = 10.0  #: NARF_P softmax temperature tau
    pose_in_color: bool = True  #: P-NeRF: pose into the colour branch (eq. D)
    box_scale_pad: float = 1.1  #: part boxes: h <- scale * h + abs
    box_abs_pad: float = 0.03  #: part boxes: additive padding (body units)
    image_size: int = 128  #: CNN baseline: side of its square bone maps and output images (paper: 128)
    latent_dim: int = 0  #: autoencoder: size of z_s and of z_a (paper 256); 0 for a per-subject fit
    encoder_channels: int = 32  #: autoencoder: image encoder base width c (paper 32: 32..512 channels)


@dataclass
class RenderConfig:
    train_coarse: int = 16  #: coarse samples per ray in training (paper 48)
    train_fine: int = 16  #: importance samples per ray in training (paper 48)
    eval_coarse: int = 16  #: coarse samples per ray in evaluation (paper 64)
    eval_fine: int = 16  #: importance samples per ray in evaluation (paper 128)
    chunk: int = 1024  #: rays per full-image rendering chunk: bounds memory; 1,024 kept a CPU faster than 4,096 (cache)
    occupancy: bool = False  #: per-subject fits: narrow each ray to its occupied stretch (docs/model.md §5)
    occupancy_resolution: int = 24  #: occupancy cells per axis of each part box
    occupancy_threshold: float = 0.5  #: density below which a cell is empty (per world unit of depth; 1 % over 2 cm)
    occupancy_every: int = 16  #: refresh the grid every n training steps
    occupancy_rounds: int = 4  #: a refresh measures 1/n of the cells, so every cell is measured every n refreshes
    grid_proposal: bool = False  #: training: importance samples follow the grid's density, no coarse field pass


@dataclass
class TrainConfig:
    steps: int = 20000  #: optimisation steps
    images_per_step: int = 16  #: images per batch (paper 16)
    rays_per_image: int = 64  #: rays per image (paper 576)
    body_fraction: float = 0.7  #: share of rays on body pixels
    border_fraction: float = 0.2  #: share on a band around the silhouette; the rest on background in the box
    lr: float = 0.01  #: Adam learning rate (equalized-lr layers assume 0.01)
    encoder_lr: float = 0.001  #: autoencoder: Adam learning rate of the image encoder (plain conv layers)
    colour_jitter: float = 0.0  #: autoencoder: per-image channel gains in [1-j, 1+j] on input and target (0: off)
    lr_decay: float = 0.99995  #: multiplicative decay per step (upstream)
    lr_min: float = 0.0  #: floor of the decayed learning rate
    adam_eps: float = 1e-12  #: Adam epsilon (upstream)
    mask_weight: float = 1.0  #: lambda_mask (0: ablation)
    checkpoint_minutes: float = 3.0  #: write a checkpoint at least this often
    validate_every: int = 1000  #: render a validation image every n steps (0: never)
    log_every: int = 50  #: write a log line every n steps
    seed: int = 0  #: seed of initialisation and ray sampling
    precision: str = "fp32"  #: fp32 (the reference) or bf16 (autocast of the training step's forward pass)
    compile: bool = False  #: torch.compile the field's forward pass (dynamic shapes; the eager path is the reference)
    deterministic: bool = True  #: deterministic kernels, so a resumed fit ends where an uninterrupted one would
    world_size: int = 1  #: processes of the fit (set from torchrun; recorded, not a setting)


@dataclass
class FitConfig:
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    train: TrainConfig = field(default_factory=TrainConfig)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _coerce(path: str, value, current):
    kind = type(current)
    if current is None:
        return value
    if kind is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"config key '{path}': expected true/false, got {value!r}")
        return value
    if kind in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"config key '{path}': expected a number, got {value!r}")
        if kind is int and float(value) != int(value):
            raise ConfigError(f"config key '{path}': expected an integer, got {value!r}")
        return kind(value)
    if kind is str and not isinstance(value, str):
        raise ConfigError(f"config key '{path}': expected a string, got {value!r}")
    return value


def _apply(target, values: dict, prefix: str = "") -> None:
    if not isinstance(values, dict):
        raise ConfigError(f"config section '{prefix or 'top level'}': expected a mapping, got {values!r}")
    names = {f.name for f in dataclasses.fields(target)}
    for key, value in values.items():
        path = f"{prefix}{key}"
        if key not in names:
            raise ConfigError(f"unknown config key '{path}' (known: {', '.join(sorted(names))})")
        current = getattr(target, key)
        if dataclasses.is_dataclass(current):
            _apply(current, value, path + ".")
        else:
            setattr(target, key, _coerce(path, value, current))


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


def load_config(preset: str | None = None, overrides: list[str] | None = None, base: dict | None = None) -> FitConfig:
    """Build a FitConfig from defaults, a base dict (a run's saved config), a preset and ``key=value`` overrides."""
    config = FitConfig()
    if base:
        _apply(config, base)
    if preset:
        path = preset_path(preset)
        try:
            values = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as err:
            raise ConfigError(f"{path}: not valid YAML ({err})") from err
        try:
            _apply(config, values)
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}") from err
    for item in overrides or []:
        if "=" not in item:
            raise ConfigError(f"override '{item}': expected section.key=value")
        key, raw = item.split("=", 1)
        parts = key.strip().split(".")
        nested: dict = {}
        cursor = nested
        for part in parts[:-1]:
            cursor = cursor.setdefault(part, {})
        cursor[parts[-1]] = yaml.safe_load(raw)
        _apply(config, nested)
    validate_config(config)
    return config


def validate_config(config: FitConfig) -> None:
    """Value checks with messages naming the key."""
    from narf.fields import ARTICULATED, IMAGE_MODELS, RIGID

    rigid = config.data.dataset == "rigid"
    allowed = RIGID if rigid else (*ARTICULATED, *IMAGE_MODELS)
    if config.model.name not in allowed:
        kind = "a rigid-object model" if rigid else "a body model"
        raise ConfigError(f"model.name: '{config.model.name}' is not {kind} ({', '.join(allowed)})")
    checks = [
        ("data.ratio", 0 < config.data.ratio <= 1),
        ("model.width", config.model.width >= 4),
        ("model.image_size", config.model.image_size >= 32 and config.model.image_size % 32 == 0),
        ("train.steps", config.train.steps >= 0),
        ("train.images_per_step", config.train.images_per_step >= 1),
        ("train.rays_per_image", config.train.rays_per_image >= 1),
        ("train.lr", config.train.lr > 0),
        ("train.lr_min", 0 <= config.train.lr_min <= config.train.lr),
        ("train.body_fraction", 0 <= config.train.body_fraction + config.train.border_fraction <= 1),
        ("render.train_coarse", config.render.train_coarse >= 2),
        ("render.eval_coarse", config.render.eval_coarse >= 2),
        ("data.protocol", config.data.protocol in ("narf", "neuralbody")),
        ("data.dataset", config.data.dataset in ("zju", "thuman", "rigid")),
        ("data.train_meshes", config.data.train_meshes >= 0),
        ("data.renders_per_mesh", config.data.renders_per_mesh >= 1),
        ("model.latent_dim", config.model.latent_dim >= 0),
        ("model.encoder_channels", config.model.encoder_channels >= 1),
        ("train.encoder_lr", config.train.encoder_lr > 0),
        ("train.colour_jitter", 0 <= config.train.colour_jitter < 1),
        ("train.precision", config.train.precision in ("fp32", "bf16")),
        ("render.occupancy_resolution", config.render.occupancy_resolution >= 2),
        ("render.occupancy_threshold", config.render.occupancy_threshold >= 0),
        ("render.occupancy_every", config.render.occupancy_every >= 1),
        ("render.occupancy_rounds", config.render.occupancy_rounds >= 1),
    ]
    for key, ok in checks:
        if not ok:
            raise ConfigError(f"config key '{key}' has an invalid value")
    autoencoder = config.data.dataset == "thuman"
    if autoencoder and config.model.latent_dim == 0:
        raise ConfigError("model.latent_dim: the thuman dataset trains an autoencoder; set a latent size (paper 256)")
    if config.render.grid_proposal and not config.render.occupancy:
        raise ConfigError("render.grid_proposal: the proposal is the occupancy grid's density; set render.occupancy")
    if config.render.occupancy and autoencoder:  # (image-space models have no rays: the switch does not apply)
        raise ConfigError("render.occupancy: the occupancy grid is for per-subject fits (densities differ per person)")
    if not autoencoder and config.model.latent_dim:
        raise ConfigError("model.latent_dim: only the thuman dataset (an autoencoder) uses latents; set it to 0")
    if config.train.colour_jitter and (not autoencoder or config.model.name == "cnn"):
        raise ConfigError("train.colour_jitter: only the NeRF-type autoencoders (the thuman dataset) use it")
