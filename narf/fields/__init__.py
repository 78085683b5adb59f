"""The NARF model family: a plain dict of model names to constructors (no string registry magic)."""

from __future__ import annotations

from functools import partial

from narf.fields.base import Cost, Field, FieldOutput
from narf.fields.cnn import CnnBaseline
from narf.fields.common import PoseBatch
from narf.fields.d_narf import DNarf
from narf.fields.narf_d import NarfD
from narf.fields.narf_h import NarfH
from narf.fields.narf_p import NarfP
from narf.fields.p_nerf import PNerf
from narf.fields.rt_nerf import RpNerf, RtNerf

#: Model name -> constructor. Keyword arguments (width, latent_dim, ...) are config values.
MODELS = {
    "narf_d": NarfD,
    "narf_d_sigmoid": partial(NarfD, selector="sigmoid"),
    "narf_h": NarfH,
    "narf_p": NarfP,
    "p_nerf": PNerf,
    "d_narf": DNarf,
    "rt_nerf": RtNerf,
    "rt_nerf_no_pose": partial(RtNerf, use_pose=False),
    "rp_nerf": RpNerf,
}
#: Model name -> the options (``model.<option>`` of a run's config) its constructor takes: building a model from a
#: config is ``build_model(name, **{option: config.model.<option> for option in MODEL_OPTIONS[name]})``.
_FIELD_OPTIONS = ("width", "density_act", "latent_dim")
MODEL_OPTIONS = {
    **{name: _FIELD_OPTIONS for name in MODELS},
    "narf_p": (*_FIELD_OPTIONS, "temperature"),
    "p_nerf": (*_FIELD_OPTIONS, "pose_in_color"),
    "cnn": ("image_size", "latent_dim"),
}
ARTICULATED = ("narf_d", "narf_d_sigmoid", "narf_h", "narf_p", "p_nerf", "d_narf")
RIGID = ("rt_nerf", "rt_nerf_no_pose", "rp_nerf")

#: Supplement cost columns (params, FLOPs per ray, memory per ray) for the paper-size presets.
PAPER_COSTS = {
    "narf_d": (1.10e6, 205e6, 382e3),
    "narf_d_sigmoid": (1.10e6, 205e6, 382e3),
    "narf_h": (1.06e6, 197e6, 344e3),
    "narf_p": (11.8e6, 2149e6, 6544e3),
    "narf_p_32": (0.32e6, 59e6, 824e3),
    "narf_p_64": (0.98e6, 178e6, 1641e3),
    "narf_p_128": (3.28e6, 596e6, 3275e3),
    "p_nerf_table": (0.85e6, 156e6, 356e3),
    "d_narf": (0.66e6, 121e6, 382e3),
}


def build_field(name: str, **kwargs) -> Field:
    """Construct a model by name, e.g. ``build_field("narf_d", width=64)``."""
    if name not in MODELS:
        raise ValueError(f"unknown model '{name}'; choose from {', '.join(MODELS)}")
    return MODELS[name](**kwargs)


#: Image-space models (not NeRF fields): name -> constructor.
IMAGE_MODELS = {"cnn": CnnBaseline}


def build_model(name: str, **kwargs):
    """Construct any model of the family by name: a NeRF field (``MODELS``) or an image model (``cnn``)."""
    if name in IMAGE_MODELS:
        return IMAGE_MODELS[name](**kwargs)
    if name not in MODELS:
        raise ValueError(f"unknown model '{name}'; choose from {', '.join([*MODELS, *IMAGE_MODELS])}")
    return build_field(name, **kwargs)


def paper_presets() -> dict[str, Field]:
    """Every paper-size configuration whose cost the supplement tabulates (plus the rigid models)."""
    presets = {name: build_field(name) for name in MODELS}
    for width in (32, 64, 128):
        presets[f"narf_p_{width}"] = build_field("narf_p", width=width)
    presets["p_nerf_table"] = build_field("p_nerf", pose_in_color=False)
    return presets


__all__ = [
    "MODELS",
    "MODEL_OPTIONS",
    "IMAGE_MODELS",
    "ARTICULATED",
    "RIGID",
    "PAPER_COSTS",
    "Cost",
    "Field",
    "FieldOutput",
    "PoseBatch",
    "build_field",
    "build_model",
    "paper_presets",
]
