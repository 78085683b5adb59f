"""The NARF model family. Each model is one entry of ``MODEL_SPECS`` (``narf/fields/models.py``): its constructor,
options, family, abilities and paper cost."""

from __future__ import annotations

from narf.fields.base import Cost, Field, FieldOutput
from narf.fields.cnn import CnnBaseline
from narf.fields.common import PoseBatch
from narf.fields.models import MODEL_SPECS, ModelSpec, PaperRow, model_names, model_spec


def build_field(name: str, **kwargs) -> Field:
    """Construct a NeRF-type model (articulated or rigid) by name, e.g. ``build_field("narf_d", width=64)``."""
    if name not in model_names("field", "rigid"):
        raise ValueError(f"unknown model '{name}'; choose from {', '.join(model_names('field', 'rigid'))}")
    return MODEL_SPECS[name].build(**kwargs)


def build_model(name: str, **kwargs):
    """Construct any model of the family by name: a NeRF field or an image model (the CNN baseline)."""
    return model_spec(name).build(**kwargs)


def paper_rows() -> list[tuple[str, PaperRow]]:
    """(model, row) for every paper-size configuration of the NeRF-type models: each model's default first, in
    table order, then the other configurations the supplement tabulates."""
    specs = [spec for spec in MODEL_SPECS.values() if spec.rays]
    return [(s.name, s.paper[0]) for s in specs] + [(s.name, row) for s in specs for row in s.paper[1:]]


def paper_presets() -> dict[str, Field]:
    """Every paper-size configuration whose cost the supplement tabulates (plus the rigid models), by row key."""
    return {row.key: build_field(name, **row.options) for name, row in paper_rows()}


__all__ = [
    "MODEL_SPECS",
    "CnnBaseline",
    "ModelSpec",
    "PaperRow",
    "Cost",
    "Field",
    "FieldOutput",
    "PoseBatch",
    "build_field",
    "build_model",
    "model_names",
    "model_spec",
    "paper_presets",
    "paper_rows",
]
