"""The supplement's claims about its tables, as checks on a table of results (docs/design.md, "Experiments").

A result table maps row name -> split -> {"mask_l2", "psnr", "ssim"}. Each check returns (holds, evidence):
holds is None when a row it needs is missing; evidence quotes the numbers it compared. The same checks run on
the supplement's own numbers (``paper_results``), where every one holds (a test asserts it).
"""

from __future__ import annotations

from collections.abc import Callable

from pipelines.experiments.tables import Table

Results = dict[str, dict[str, dict[str, float]]]


def paper_results(table: Table) -> Results:
    """The supplement's cells of ``table`` in the result layout."""
    keys = ("mask_l2", "psnr", "ssim")
    return {
        row.name: {split: dict(zip(keys, cell)) for split, cell in zip(table.splits, row.paper)}
        for row in table.rows
        if row.paper is not None
    }


def _mean(results: Results, row: str, metric: str = "psnr") -> float:
    return sum(cell[metric] for cell in results[row].values()) / len(results[row])


def _need(results: Results, rows: list[str]) -> bool:
    return all(r in results for r in rows)


def rt_nerf_order(r: Results):
    if not _need(r, ["rt_nerf", "rt_nerf_no_pose", "rp_nerf"]):
        return None, "needs rt_nerf, rt_nerf_no_pose, rp_nerf"
    rt, no_xi, rp = (r[k]["test"] for k in ("rt_nerf", "rt_nerf_no_pose", "rp_nerf"))
    holds = rt["mask_l2"] < no_xi["mask_l2"] and no_xi["psnr"] > rp["psnr"] and no_xi["mask_l2"] < rp["mask_l2"]
    cells = " > ".join(f"{c['mask_l2']:.1f}/{c['psnr']:.2f}" for c in (rt, no_xi, rp))
    return holds, f"Mask L2/PSNR {cells}"


def rp_nerf_fails(r: Results):
    if not _need(r, ["rt_nerf", "rp_nerf"]):
        return None, "needs rt_nerf, rp_nerf"
    gap = r["rt_nerf"]["test"]["psnr"] - r["rp_nerf"]["test"]["psnr"]
    return gap >= 3.0, f"RT-NeRF - RP-NeRF = {gap:.2f} dB (fails: >= 3 dB)"


def _best_on(r: Results, row: str, rivals: list[str], splits: list[str]):
    present = [x for x in rivals if x in r]
    if row not in r or not present:
        return None, f"needs {row} and at least one of {', '.join(rivals)}"
    parts, holds = [], True
    for split in splits:
        best = max(present, key=lambda x: r[x][split]["psnr"])
        holds &= r[row][split]["psnr"] >= r[best][split]["psnr"]
        parts.append(f"{split}: {r[row][split]['psnr']:.2f} vs best other {best} {r[best][split]['psnr']:.2f}")
    return holds, "; ".join(parts)


def narf_d_best_novel_pose(r: Results):
    rivals = ["cnn", "p_nerf", "d_narf", "narf_p", "narf_h"]
    return _best_on(r, "narf_d", rivals, ["novel_pose_same_view", "novel_pose_novel_view"])


def narf_d_best_everywhere(r: Results):
    rivals = ["p_nerf", "d_narf", "narf_p", "narf_h"]
    return _best_on(r, "narf_d", rivals, list(next(iter(r.values())).keys()) if r else [])


def narf_h_degrades(r: Results):
    if not _need(r, ["narf_h", "narf_d"]):
        return None, "needs narf_h, narf_d"
    drop = {k: r[k]["same_pose_same_view"]["psnr"] - r[k]["novel_pose_same_view"]["psnr"] for k in ("narf_h", "narf_d")}
    holds = drop["narf_h"] >= drop["narf_d"] + 1.0
    return holds, f"SS -> NS PSNR drop: NARF_H {drop['narf_h']:.2f} dB, NARF_D {drop['narf_d']:.2f} dB (>= 1 dB more)"


def mask_loss_helps(r: Results):
    ablations = (("narf_p_32", "p32_no_mask"), ("narf_h", "narf_h_no_mask"), ("narf_d", "narf_d_no_mask"))
    pairs = [(a, b) for a, b in ablations if _need(r, [a, b])]
    if not pairs:
        return None, "needs a row and its w/o L_mask ablation"
    holds, parts = True, []
    for a, b in pairs:
        worse_mask = all(r[b][s]["mask_l2"] > r[a][s]["mask_l2"] for s in r[a])
        nn = "novel_pose_novel_view"
        holds &= worse_mask and r[b][nn]["psnr"] < r[a][nn]["psnr"]
        before, after = (f"{r[x][nn]['mask_l2']:.1f}/{r[x][nn]['psnr']:.2f}" for x in (a, b))
        parts.append(f"{a}: NN {before} -> {after}")
    return holds, "Mask L2 worse on every split and NN PSNR lower without it; " + "; ".join(parts)


def softmax_beats_sigmoid(r: Results):
    if not _need(r, ["narf_d", "narf_d_sigmoid"]):
        return None, "needs narf_d, narf_d_sigmoid"
    nn = "novel_pose_novel_view"
    a, b = r["narf_d"][nn]["psnr"], r["narf_d_sigmoid"][nn]["psnr"]
    return a >= b, f"NN PSNR softmax {a:.2f} vs sigmoid {b:.2f}"


_TAUS = {
    "p32_tau_0.01": 0.01,
    "p32_tau_0.1": 0.1,
    "p32_tau_1": 1,
    "narf_p_32": 10,
    "p32_tau_100": 100,
    "p32_tau_1000": 1000,
}


def tau_100_best(r: Results):
    if not _need(r, ["p32_tau_100", "p32_tau_0.01", "p32_tau_1000"]):
        return None, "needs tau 0.01, 100 and 1000"
    means = {tau: _mean(r, row) for row, tau in _TAUS.items() if row in r}
    holds = max(means, key=means.get) == 100
    return holds, "mean PSNR by tau: " + ", ".join(f"{t:g}: {m:.2f}" for t, m in means.items())


def narf_p_width(r: Results):
    rows = [x for x in ("narf_p_32", "narf_p_64", "narf_p_128", "narf_p") if x in r]
    if len(rows) < 2:
        return None, "needs two NARF_P widths"
    means = [_mean(r, x) for x in rows]
    holds = all(b >= a for a, b in zip(means, means[1:]))
    return holds, "mean PSNR by width: " + ", ".join(f"{x}: {m:.2f}" for x, m in zip(rows, means))


def baselines_fail(r: Results):
    present = [x for x in ("p_nerf", "d_narf") if x in r]
    if "narf_d" not in r or not present:
        return None, "needs narf_d and p_nerf or d_narf"
    gaps = {x: _mean(r, "narf_d") - _mean(r, x) for x in present}
    return all(g >= 3.0 for g in gaps.values()), ", ".join(f"NARF_D - {x} = {g:.2f} dB" for x, g in gaps.items())


def cnn_mask_collapses(r: Results):
    if not _need(r, ["cnn", "narf_d"]):
        return None, "needs cnn, narf_d"
    ratio = {
        k: r[k]["same_pose_novel_view"]["mask_l2"] / max(r[k]["same_pose_same_view"]["mask_l2"], 1e-9)
        for k in ("cnn", "narf_d")
    }
    holds = ratio["cnn"] >= 2.0 and ratio["cnn"] > ratio["narf_d"]
    return holds, f"Mask L2 SN / SS: CNN {ratio['cnn']:.2f}, NARF_D {ratio['narf_d']:.2f}"


Check = tuple[str, Callable[[Results], tuple[bool | None, str]]]
ORDERINGS: dict[str, list[Check]] = {
    "table-b": [("RT-NeRF > RT-NeRF w/o xi (Mask L2) > RP-NeRF", rt_nerf_order), ("RP-NeRF fails", rp_nerf_fails)],
    "table-c": [
        ("NARF_D best on the novel-pose splits", narf_d_best_novel_pose),
        ("NARF_H degrades on novel pose", narf_h_degrades),
        ("removing the mask loss hurts", mask_loss_helps),
        ("softmax >= sigmoid", softmax_beats_sigmoid),
        ("tau = 100 best, both extremes worse", tau_100_best),
        ("NARF_P improves with width", narf_p_width),
        ("P-NeRF and D-NARF fail", baselines_fail),
        ("the CNN's Mask L2 collapses under novel views", cnn_mask_collapses),
    ],
    "table-a": [
        ("NARF_D best on every split (NeRF-type models)", narf_d_best_everywhere),
        ("P-NeRF and D-NARF fail", baselines_fail),
    ],
}


def check_orderings(table_name: str, results: Results) -> list[dict]:
    """Every ordering of a table on ``results``: [{"claim", "holds", "evidence"}]."""
    return [
        {"claim": claim, **dict(zip(("holds", "evidence"), check(results)))} for claim, check in ORDERINGS[table_name]
    ]
