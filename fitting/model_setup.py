"""A config's model as training and evaluation see it: built with the options its constructor takes, then told
what its colour may depend on and how far its point encoding is open at a step (docs/model.md §2, §4)."""

from __future__ import annotations

import math

from fitting.config import FitConfig
from narf.encodings import POINT_FREQS
from narf.fields import model_spec
from narf.occupancy import OccupancyGrid


def make_field(config: FitConfig, step: int = 0):
    """The model of a config, given the options its constructor takes (its spec in ``narf.fields.MODEL_SPECS``), as
    it is at ``step`` (:func:`configure_field`)."""
    m = config.model
    spec = model_spec(m.name)
    field = spec.build(**{option: getattr(m, option) for option in spec.options})
    if not spec.rays:
        return field
    configure_field(field, config, step)
    r = config.render
    if r.occupancy:
        field.occupancy = OccupancyGrid(field.n_parts, r.occupancy_resolution, r.occupancy_threshold)
    return field


def encoding_window(config: FitConfig, step: int) -> float | None:
    """The coarse-to-fine window's alpha at ``step``: from ``train.window_start`` to all 10 frequencies of gamma_10,
    linearly over ``train.window_steps`` (docs/model.md §2); None once open (or when the window is off)."""
    t = config.train
    if t.window_steps <= 0 or step >= t.window_steps:
        return None
    return t.window_start + (POINT_FREQS - t.window_start) * step / t.window_steps


def configure_field(field, config: FitConfig, step: int) -> None:
    """Set what a field's colour may depend on (the model config) and its point encoding's window at ``step``.
    Training and evaluation both come through here, so a run evaluated at step n sees the field it trained."""
    m = config.model
    field.view_freqs, field.view_jitter, field.pose_dropout = m.view_freqs, math.radians(m.view_jitter), m.pose_dropout
    field.pose_freqs = m.pose_freqs
    field.point_window = encoding_window(config, step)
