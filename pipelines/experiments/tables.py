"""The NARF supplement's tables as experiment definitions: rows (how to fit each one), the supplement's numbers
(Mask L2 x10^4 / PSNR / SSIM per split, as the NARF supplement prints them in its Tables A, B and C),
and the orderings that the supplement's text draws from them (docs/design.md, "Experiments")."""

from __future__ import annotations

from dataclasses import dataclass, field

#: Split keys of the articulated tables, in the supplement's column order (SS, NS, SN, NN).
POSE_VIEW_SPLITS = ("same_pose_same_view", "novel_pose_same_view", "same_pose_novel_view", "novel_pose_novel_view")
SHORT = {
    "same_pose_same_view": "SS",
    "novel_pose_same_view": "NS",
    "same_pose_novel_view": "SN",
    "novel_pose_novel_view": "NN",
    "test": "test",
}


@dataclass(frozen=True)
class RowFit:
    """How a row is fitted beside its table's preset: the ``model`` and its ``sets`` (``section.key=value``)."""

    model: str
    sets: tuple[str, ...] = ()


@dataclass(frozen=True)
class Row:
    """One row: ``name`` (folder and key), ``label`` (as the supplement prints it), ``fit`` (model and settings
    besides the preset), ``paper``: the supplement's cells per split (mask_l2, psnr, ssim), or None where it has
    none; ``paper_cost``: its (#params, FLOPs/ray, memory/ray) or None."""

    name: str
    label: str
    fit: RowFit
    paper: tuple[tuple[float, float, float], ...] | None = None
    paper_cost: tuple[float, float, float] | None = None

    @property
    def fit_args(self) -> tuple[str, ...]:
        """The row's fit as ``narf-fit`` flags (what ``--list`` prints and a result records)."""
        return ("--model", self.fit.model, *(arg for s in self.fit.sets for arg in ("--set", s)))


@dataclass(frozen=True)
class Table:
    """A table: the ``kind`` of its runs (``pipelines.runs.kinds``), the splits it reports and its rows."""

    name: str
    title: str
    kind: str
    splits: tuple[str, ...]
    rows: tuple[Row, ...]
    notes: tuple[str, ...] = field(default=())


def _model(name: str, *sets: str) -> RowFit:
    return RowFit(name, sets)


_D, _H = (1.10e6, 205e6, 382e3), (1.06e6, 197e6, 344e3)
_P32 = (0.32e6, 59e6, 824e3)
_NO_MASK = "train.mask_weight=0"

TABLE_B = Table(
    "table-b",
    "Table B: rigid object (RP-NeRF, RT-NeRF w/o xi, RT-NeRF)",
    "rigid",
    ("test",),
    (
        Row("rp_nerf", "RP-NeRF", _model("rp_nerf"), ((4511.0, 11.25, 0.3103),)),
        Row("rt_nerf_no_pose", "RT-NeRF w/o xi", _model("rt_nerf_no_pose"), ((29.2, 19.83, 0.8255),)),
        Row("rt_nerf", "RT-NeRF", _model("rt_nerf"), ((16.9, 20.05, 0.8388),)),
    ),
)

_C_ROWS = [
    (
        "cnn",
        "CNN",
        _model("cnn"),
        [(76.9, 29.12, 0.9429), (134.8, 27.30, 0.9211), (365.9, 25.19, 0.8532), (392.2, 24.53, 0.8470)],
        (15.6e6, 0, 0),
    ),
    (
        "p_nerf",
        "P-NeRF",
        _model("p_nerf"),
        [(778.7, 21.42, 0.8006), (1077.0, 20.42, 0.7696), (844.9, 21.19, 0.7897), (1110.1, 20.27, 0.7648)],
        (0.85e6, 156e6, 356e3),
    ),
    (
        "d_narf",
        "D-NARF",
        _model("d_narf"),
        [(2182.6, 18.90, 0.1143), (2308.2, 18.81, 0.1140), (2137.3, 19.09, 0.1144), (2241.3, 18.88, 0.1133)],
        (0.66e6, 121e6, 382e3),
    ),
    (
        "narf_p",
        "NARF_P (=P 256)",
        _model("narf_p", "model.width=256"),
        [(92.0, 28.56, 0.9258), (116.2, 26.83, 0.9052), (101.5, 27.54, 0.9144), (125.8, 26.50, 0.9104)],
        (11.8e6, 2149e6, 6544e3),
    ),
    (
        "narf_h",
        "NARF_H",
        _model("narf_h"),
        [(55.6, 29.91, 0.9470), (376.8, 24.09, 0.8665), (70.5, 28.81, 0.9370), (374.6, 23.98, 0.8646)],
        _H,
    ),
    (
        "narf_d",
        "NARF_D",
        _model("narf_d"),
        [(50.5, 30.86, 0.9586), (114.4, 27.93, 0.9317), (64.1, 29.44, 0.9466), (123.8, 27.24, 0.9230)],
        _D,
    ),
    (
        "narf_d_sigmoid",
        "NARF_D sigmoid",
        _model("narf_d_sigmoid"),
        [(50.8, 30.74, 0.9578), (117.7, 27.83, 0.9304), (64.6, 29.35, 0.9459), (125.4, 26.17, 0.9129)],
        _D,
    ),
    (
        "narf_p_32",
        "NARF_P 32 (=tau 10)",
        _model("narf_p", "model.width=32"),
        [(114.8, 27.85, 0.9191), (139.9, 26.86, 0.9068), (122.9, 27.14, 0.9105), (147.3, 25.74, 0.8933)],
        _P32,
    ),
    (
        "narf_p_64",
        "NARF_P 64",
        _model("narf_p", "model.width=64"),
        [(105.5, 27.86, 0.9212), (126.9, 26.78, 0.9094), (113.8, 27.21, 0.9127), (133.1, 26.28, 0.9041)],
        (0.98e6, 178e6, 1641e3),
    ),
    (
        "narf_p_128",
        "NARF_P 128",
        _model("narf_p", "model.width=128"),
        [(93.8, 28.46, 0.9284), (116.1, 27.15, 0.9135), (102.9, 27.56, 0.9180), (124.2, 26.23, 0.9068)],
        (3.28e6, 596e6, 3275e3),
    ),
    (
        "p32_tau_0.01",
        "P32 tau 0.01",
        _model("narf_p", "model.width=32", "model.temperature=0.01"),
        [(240.1, 25.81, 0.8730), (282.0, 24.92, 0.8541), (256.0, 25.32, 0.8624), (287.9, 23.72, 0.8333)],
        _P32,
    ),
    (
        "p32_tau_0.1",
        "P32 tau 0.1",
        _model("narf_p", "model.width=32", "model.temperature=0.1"),
        [(168.1, 26.79, 0.8995), (196.7, 25.92, 0.8863), (176.1, 26.26, 0.8911), (204.8, 25.10, 0.8756)],
        _P32,
    ),
    (
        "p32_tau_1",
        "P32 tau 1",
        _model("narf_p", "model.width=32", "model.temperature=1"),
        [(141.5, 27.24, 0.9077), (169.9, 26.29, 0.8949), (150.9, 26.56, 0.8989), (178.2, 25.16, 0.8809)],
        _P32,
    ),
    (
        "p32_tau_100",
        "P32 tau 100",
        _model("narf_p", "model.width=32", "model.temperature=100"),
        [(107.9, 27.83, 0.9190), (130.2, 26.96, 0.9059), (115.9, 27.23, 0.9117), (137.5, 26.24, 0.8983)],
        _P32,
    ),
    (
        "p32_tau_1000",
        "P32 tau 1000",
        _model("narf_p", "model.width=32", "model.temperature=1000"),
        [(109.0, 27.44, 0.9137), (130.8, 26.68, 0.9014), (117.0, 26.91, 0.9072), (138.3, 26.08, 0.8953)],
        _P32,
    ),
    (
        "p32_no_mask",
        "P32 w/o L_mask",
        _model("narf_p", "model.width=32", _NO_MASK),
        [(193.9, 28.01, 0.9131), (220.2, 26.72, 0.8994), (208.7, 27.33, 0.9028), (229.8, 25.54, 0.8792)],
        _P32,
    ),
    (
        "narf_h_no_mask",
        "NARF_H w/o L_mask",
        _model("narf_h", _NO_MASK),
        [(6816.2, 24.25, 0.7004), (6893.1, 21.10, 0.6636), (6876.3, 23.40, 0.7029), (6957.2, 20.53, 0.5244)],
        _H,
    ),
    (
        "narf_d_no_mask",
        "NARF_D w/o L_mask",
        _model("narf_d", _NO_MASK),
        [(113.4, 31.39, 0.9630), (165.7, 28.09, 0.9346), (132.8, 29.90, 0.9508), (263.7, 25.71, 0.8889)],
        _D,
    ),
]
TABLE_C = Table(
    "table-c",
    "Table C: single articulated subject (synthetic taichi)",
    "subject",
    POSE_VIEW_SPLITS,
    tuple(Row(name, label, args, tuple(paper), cost) for name, label, args, paper, cost in _C_ROWS),
    ("NARF_P rows keep the supplement's widths (32-256); every other NeRF-type row uses the preset's width.",),
)

_A_ROWS = [
    (
        "cnn",
        "CNN",
        _model("cnn"),
        [(89.0, 25.59, 0.8966), (157.2, 24.70, 0.8757), (385.0, 22.70, 0.8213), (381.5, 22.98, 0.8243)],
        (15.6e6, 0, 0),
    ),
    (
        "p_nerf",
        "P-NeRF",
        _model("p_nerf"),
        [(1526.6, 19.24, 0.5362), (1572.1, 19.60, 0.5346), (1911.3, 18.13, 0.4666), (1963.2, 19.08, 0.4746)],
        (0.85e6, 156e6, 356e3),
    ),
    (
        "d_narf",
        "D-NARF",
        _model("d_narf"),
        [(2067.2, 18.27, 0.6733), (2060.2, 18.81, 0.6706), (2026.7, 18.00, 0.5983), (2049.5, 18.82, 0.6121)],
        (0.66e6, 121e6, 382e3),
    ),
    (
        "narf_p",
        "NARF_P",
        _model("narf_p"),
        [(159.5, 22.57, 0.8250), (182.3, 22.58, 0.8211), (196.4, 21.32, 0.8056), (205.0, 21.80, 0.8088)],
        (11.8e6, 2140e6, 6544e3),
    ),
    (
        "narf_h",
        "NARF_H",
        _model("narf_h"),
        [(201.1, 22.89, 0.8244), (225.1, 23.14, 0.8205), (265.1, 21.48, 0.7891), (275.1, 22.36, 0.7961)],
        _H,
    ),
    (
        "narf_d",
        "NARF_D",
        _model("narf_d"),
        [(123.4, 23.84, 0.8568), (163.5, 23.55, 0.8435), (166.2, 22.25, 0.8313), (186.3, 22.81, 0.8294)],
        _D,
    ),
]
TABLE_A = Table(
    "table-a",
    "Table A: autoencoder across people (synthetic THUman)",
    "autoencoder",
    POSE_VIEW_SPLITS,
    tuple(Row(name, label, args, tuple(paper), cost) for name, label, args, paper, cost in _A_ROWS),
    (
        "The CNN row is the CNN baseline conditioned on the image encoder's code (docs/model.md §4). The "
        "supplement's CNN row beats its NARF_D on PSNR and SSIM although its text calls NARF_D best; the "
        "ordering checked here is among the NeRF-type models.",
    ),
)

TABLES = {t.name: t for t in (TABLE_A, TABLE_B, TABLE_C)}
