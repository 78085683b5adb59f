"""The NARF model family, one table: for each model its constructor, the config options it takes, its family,
what it can render or export, and the supplement's cost of its paper-size configurations (Tables A and C).

Every question about a model (may it run in a rigid run? does it render rays, depth, parts? can a mesh be
extracted from it?) is a lookup in :data:`MODEL_SPECS`, never a test of its name."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Literal

from narf.fields.cnn import CnnBaseline
from narf.fields.d_narf import DNarf
from narf.fields.narf_d import NarfD
from narf.fields.narf_h import NarfH
from narf.fields.narf_p import NarfP
from narf.fields.p_nerf import PNerf
from narf.fields.rt_nerf import RpNerf, RtNerf

#: field: an articulated radiance field (rays; depth, parts, meshes); image: an image-space model (the CNN
#: baseline, no rays); rigid: a rigid-object field (supplement Table B).
Family = Literal["field", "image", "rigid"]
#: Supplement cost columns: parameters, FLOPs per ray, activation memory per ray.
PaperCost = tuple[float, float | None, float | None]


@dataclass(frozen=True)
class PaperRow:
    """One paper-size configuration of a model: its key (``narf-cost --model``), its label in ``narf-cost``'s table,
    the supplement's cost (None where the tables have no row) and the constructor options that make it (besides
    the defaults)."""

    key: str
    label: str
    cost: PaperCost | None = None
    options: dict = field(default_factory=dict)


@dataclass(frozen=True)
class ModelSpec:
    """One model. ``build(**{option: config.model.<option> for option in options})`` constructs it; ``paper``: its
    paper-size rows, the default configuration first (keyed by the model's name in ``paper_presets``)."""

    name: str
    build: Callable
    options: tuple[str, ...]
    family: Family
    paper: tuple[PaperRow, ...]

    @property
    def rays(self) -> bool:
        """Renders rays through a density field (depth, part segmentation, code refinement, the viewer)."""
        return self.family != "image"

    @property
    def pose_in_density(self) -> bool:
        """Its density reads the pose features xi (what the colour may do with xi would reach the geometry too); a
        model whose class does not say (the CNN baseline) counts as reading them."""
        return getattr(getattr(self.build, "func", self.build), "pose_in_density", True)

    @property
    def meshes(self) -> bool:
        """A surface can be extracted from it (``narf-export-mesh``, ``narf-eval --mesh``), rigged included."""
        return self.family == "field"


_FIELD_OPTIONS = ("width", "density_act", "latent_dim", "appearance_dim")


def _field(name, build, label, cost=None, extra=(), family: Family = "field", variants=()) -> ModelSpec:
    return ModelSpec(name, build, (*_FIELD_OPTIONS, *extra), family, (PaperRow(name, label, cost), *variants))


_NARF_D_COST = (1.10e6, 205e6, 382e3)
#: NARF_D's departures from the paper, off by default (docs/model.md §2, *Part grids*): its point encoding (the
#: paper's is ``frequency``), the trunk's residual blocks (the paper's 3) and the shading (the paper has none)
_NARF_D_OPTIONS = (
    "encoding",
    "grid_levels",
    "grid_features",
    "grid_min_resolution",
    "grid_max_resolution",
    "grid_log2_rows",
    "trunk_blocks",
    "shading",
)

#: Model name -> spec, in ``narf-cost``'s order.
MODEL_SPECS: dict[str, ModelSpec] = {
    spec.name: spec
    for spec in (
        _field("narf_d", NarfD, "NARF_D", _NARF_D_COST, _NARF_D_OPTIONS),
        _field("narf_d_sigmoid", partial(NarfD, selector="sigmoid"), "NARF_D sigmoid", _NARF_D_COST, _NARF_D_OPTIONS),
        _field("narf_h", NarfH, "NARF_H", (1.06e6, 197e6, 344e3)),
        _field(
            "narf_p",
            NarfP,
            "NARF_P (256)",
            (11.8e6, 2149e6, 6544e3),
            ("temperature",),
            variants=(
                PaperRow("narf_p_32", "NARF_P (32)", (0.32e6, 59e6, 824e3), {"width": 32}),
                PaperRow("narf_p_64", "NARF_P (64)", (0.98e6, 178e6, 1641e3), {"width": 64}),
                PaperRow("narf_p_128", "NARF_P (128)", (3.28e6, 596e6, 3275e3), {"width": 128}),
            ),
        ),
        _field(
            "p_nerf",
            PNerf,
            "P-NeRF (pose in colour, eq. D)",
            extra=("pose_in_color",),
            variants=(
                PaperRow(
                    "p_nerf_table",
                    "P-NeRF (pose_in_color=false, as tables)",
                    (0.85e6, 156e6, 356e3),
                    {"pose_in_color": False},
                ),
            ),
        ),
        _field("d_narf", DNarf, "D-NARF", (0.66e6, 121e6, 382e3)),
        _field("rt_nerf", RtNerf, "RT-NeRF", family="rigid"),
        _field("rt_nerf_no_pose", partial(RtNerf, use_pose=False), "RT-NeRF w/o xi", family="rigid"),
        _field("rp_nerf", RpNerf, "RP-NeRF", family="rigid"),
        ModelSpec(
            "cnn",
            CnnBaseline,
            ("image_size", "latent_dim"),
            "image",
            (PaperRow("cnn", "CNN baseline", (15.6e6, None, None)),),
        ),
    )
}


def model_spec(name: str) -> ModelSpec:
    """The spec of model ``name``; an unknown name is a ValueError listing the models."""
    if name not in MODEL_SPECS:
        raise ValueError(f"unknown model '{name}'; choose from {', '.join(MODEL_SPECS)}")
    return MODEL_SPECS[name]


def model_names(*families: Family) -> tuple[str, ...]:
    """The models of ``families`` (all models without arguments), in table order."""
    return tuple(name for name, spec in MODEL_SPECS.items() if not families or spec.family in families)
