"""``make reference REV=<revision>``: show that a change leaves behaviour unchanged.

The same fixed-seed tiny work runs twice, on one input: once with the working tree's code and once with the code
of a chosen git revision, checked out in a worktree under ``--work``. The work, for every body model (the NeRF-type
ones and the CNN; the rigid RT-NeRF variants fit other data): a 4-step ``narf-fit`` on a 64^2 synthetic capture,
``narf-eval`` of one novel_pose view, a 2-frame orbit video and, for the NeRF-type models, a 32^3 mesh. Beside them,
``narf-prepare-capture`` of a small synthetic recording (4 cameras x 10 frames at 256^2, videos and a Qualisys file)
from its keypoint files and masks, once with the followed person alone and once with two passers-by in the files,
and through the detector where mediapipe is installed. The inputs are generated once by the working tree, so a
difference comes from fitting, evaluation, rendering, export or preparation, never from the data.

Compared, artefact by artefact:

* checkpoint tensors with ``torch.equal`` (weights, optimiser state);
* ``eval/metrics.json`` numbers for exact equality (paths, versions and times left out);
* videos, meshes and ``log.jsonl`` rows (times left out) byte for byte;
* a prepared capture file by file: JSON for equality (times, paths and versions left out), every other file byte for
  byte.

Prints one table and exits 1 when anything differs. Both trees run with the same virtualenv and one thread, so the
only difference is the code. The revision must have the same command-line flags (any revision since they exist).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODELS = ("narf_d", "narf_d_sigmoid", "narf_h", "narf_p", "p_nerf", "d_narf", "cnn")
#: keys whose values name places, machines or times, not behaviour
VOLATILE = {"run", "subject", "versions", "elapsed_s", "rays_per_s", "seconds", "time_s", "device", "capture", "cache"}
#: the prepares compared: name -> (passers-by in the recording, through the detector)
PREPARES = {"files": (0, False), "files_with_passers_by": (2, False), "detector": (0, True)}
#: a prepare short enough for a reference (the body fit's iterations; the same in both trees)
PREPARE_FLAGS = ["--quiet", "--fit-iterations", "200", "--silhouette-iterations", "100"]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m bench.reference", description=__doc__.split("\n\n")[0])
    parser.add_argument("--rev", default="HEAD", help="git revision to compare the working tree with")
    parser.add_argument("--work", type=Path, default=None, help="scratch folder (default: a temporary one)")
    parser.add_argument("--models", nargs="*", default=list(MODELS), choices=MODELS, help="models to run")
    parser.add_argument("--prepares", nargs="*", default=list(PREPARES), choices=PREPARES, help="prepares to run")
    return parser


def _run(tree: Path, argv: list[str], env: dict) -> None:
    """``pipelines.cli.<argv[0]>``'s entry point with the code of ``tree``, or ``-m MODULE`` for a module's main."""
    module = argv[0]
    if module == "-m":
        command = [sys.executable, "-m", *argv[1:]]
    else:
        command = [sys.executable, "-c", f"from pipelines.cli.{module} import entrypoint; entrypoint()", *argv[1:]]
    done = subprocess.run(command, cwd=tree, env={**env, "PYTHONPATH": str(tree)}, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{tree}: {' '.join(argv[:2])} failed: {done.stderr.strip().splitlines()[-1:]}")


def _work(tree: Path, data: Path, out: Path, model: str, env: dict) -> None:
    """The fixed-seed work of one model with the code of ``tree`` into ``out``."""
    run = out / model
    sets = ["data.ratio=1.0", "train.steps=4", "train.validate_every=0", "train.log_every=1"]
    flags = [x for s in sets for x in ("--set", s)]
    _run(tree, ["fit", "--config", "tiny", "--model", model, "--data-root", str(data), "--out", str(run), *flags], env)
    _run(tree, ["eval", "--run", str(run), "--split", "novel_pose", "--limit", "1", "--grids", "0", "--quiet"], env)
    video = ["render_video", "--run", str(run), "--kind", "orbit", "--frames", "2", "--quiet"]
    _run(tree, [*video, "--out", str(run / "orbit.mp4")], env)
    if model != "cnn":
        mesh = ["export_mesh", "--run", str(run), "--frame", "0", "--resolution", "32", "--quiet"]
        _run(tree, [*mesh, "--out", str(run / "mesh.ply")], env)


def _recordings(data: Path, work: Path, env: dict) -> dict[int, Path]:
    """The synthetic recordings the prepares read, by their passers-by, written once by the working tree."""
    synth = ["synth", "--data-root", str(data / "recording"), "--resolution", "256", "--frames", "10", "--cameras"]
    _run(ROOT, [*synth, "4", "--calib-shots", "0", "--calib-close-ups", "0", "--workers", "1"], env)
    capture = data / "recording" / "synthetic" / "taichi"
    out = {}
    for people in sorted({p for p, _ in PREPARES.values()}):
        out[people] = work / f"recording-{people}"
        if not out[people].exists():
            args = [str(capture), str(out[people]), "--people", str(people + 1)]
            _run(ROOT, ["-m", "pipelines.synthetic.recording", *args], env)
    return out


def _prepare(tree: Path, recording: Path, out: Path, detector: bool, env: dict) -> None:
    """One fixed prepare of ``recording`` with the code of ``tree`` into ``out``."""
    files = [] if detector else ["--keypoints", str(recording / "keypoints"), "--masks", str(recording / "masks")]
    _run(tree, ["prepare_capture", str(recording), "--out", str(out), *files, *PREPARE_FLAGS], env)


def _compare_captures(a: Path, b: Path) -> list[tuple[str, str]]:
    """(artefact, verdict) for two prepared captures: the list of files, then every file."""
    names = [sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()) for root in (a, b)]
    if names[0] != names[1]:
        return [("files", f"differ: {sorted(set(names[0]) ^ set(names[1]))[:5]}")]
    differ = []
    for name in names[0]:
        if name.endswith(".json"):
            same = _stable(json.loads((a / name).read_text())) == _stable(json.loads((b / name).read_text()))
        else:
            same = (a / name).read_bytes() == (b / name).read_bytes()
        if not same:
            differ.append(name)
    verdict = "same" if not differ else f"differs: {', '.join(differ[:5])}" + (" ..." if len(differ) > 5 else "")
    return [(f"{len(names[0])} files", verdict)]


def _stable(value):
    """A JSON value without its volatile keys."""
    if isinstance(value, dict):
        return {k: _stable(v) for k, v in value.items() if k not in VOLATILE}
    if isinstance(value, list):
        return [_stable(v) for v in value]
    return value


def _compare(a: Path, b: Path) -> list[tuple[str, str]]:
    """(artefact, 'same' or what differs) for one model's two output folders."""
    import torch

    rows = []
    first = torch.load(a / "checkpoint.pt", map_location="cpu", weights_only=True)
    second = torch.load(b / "checkpoint.pt", map_location="cpu", weights_only=True)
    differ = [k for k in ("model", "optimizer") if not _equal(first.get(k), second.get(k))]
    rows.append(("checkpoint", "same" if not differ else "differs: " + ", ".join(differ)))
    metrics = [_stable(json.loads((p / "eval" / "metrics.json").read_text())) for p in (a, b)]
    rows.append(("eval/metrics.json", "same" if metrics[0] == metrics[1] else "differs"))
    logs = [[_stable(json.loads(line)) for line in (p / "log.jsonl").read_text().splitlines()] for p in (a, b)]
    rows.append(("log.jsonl", "same" if logs[0] == logs[1] else "differs"))
    for name in ("orbit.mp4", "mesh.ply"):
        if (a / name).exists() or (b / name).exists():
            same = (a / name).is_file() and (b / name).is_file() and (a / name).read_bytes() == (b / name).read_bytes()
            rows.append((name, "same" if same else "differs"))
    return rows


def _equal(x, y) -> bool:
    """Nested dicts / lists of tensors and numbers, compared with ``torch.equal``."""
    import torch

    if isinstance(x, torch.Tensor) and isinstance(y, torch.Tensor):
        return x.dtype == y.dtype and x.shape == y.shape and torch.equal(x, y)
    if isinstance(x, dict) and isinstance(y, dict):
        return x.keys() == y.keys() and all(_equal(x[k], y[k]) for k in x)
    if isinstance(x, (list, tuple)) and isinstance(y, (list, tuple)):
        return len(x) == len(y) and all(_equal(u, v) for u, v in zip(x, y))
    return x == y


def _prepares(names: list[str], old: Path, work: Path, env: dict) -> bool:
    """Run and compare the named prepares in both trees; print a row each; True when any differs."""
    import importlib.util

    has_detector = importlib.util.find_spec("mediapipe") is not None
    wanted = [n for n in names if has_detector or not PREPARES[n][1]]
    if len(wanted) < len(names):
        print("| prepare: detector | - | skipped: mediapipe is not installed (make venv-real) |", flush=True)
    recordings = _recordings(work / "data", work, env) if wanted else {}
    failed = False
    for name in wanted:
        people, detector = PREPARES[name]
        for tree, side in ((ROOT, "new"), (old, "old")):
            _prepare(tree, recordings[people], work / side / f"prepare-{name}", detector, env)
        for artefact, verdict in _compare_captures(work / "new" / f"prepare-{name}", work / "old" / f"prepare-{name}"):
            failed |= verdict != "same"
            print(f"| prepare: {name} | {artefact} | {verdict} |", flush=True)
    return failed


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="narf-reference-") as scratch:
        work = args.work or Path(scratch)
        rev = subprocess.run(["git", "rev-parse", args.rev], cwd=ROOT, capture_output=True, text=True, check=True)
        sha = rev.stdout.strip()
        old = work / f"rev-{sha[:12]}"
        if not old.exists():
            subprocess.run(["git", "worktree", "add", "--detach", str(old), sha], cwd=ROOT, check=True)
        env = {**os.environ, "OMP_NUM_THREADS": "1", "NARF_CACHE": str(work / "cache")}
        data = work / "data"
        synth = ["synth", "--data-root", str(data), "--resolution", "64", "--frames", "6", "--cameras", "4"]
        _run(ROOT, [*synth, "--calib-shots", "0", "--calib-close-ups", "0", "--workers", "1"], env)
        failed = False
        print(f"| work | artefact | working tree against {args.rev} ({sha[:12]}) |\n|---|---|---|")
        try:
            failed |= _prepares(args.prepares, old, work, env)
            for model in args.models:
                for tree, out in ((ROOT, work / "new"), (old, work / "old")):
                    _work(tree, data, out, model, env)
                for artefact, verdict in _compare(work / "new" / model, work / "old" / model):
                    failed |= verdict != "same"
                    print(f"| {model} | {artefact} | {verdict} |", flush=True)
        finally:
            if args.work is None:
                subprocess.run(["git", "worktree", "remove", "--force", str(old)], cwd=ROOT, check=False)
    return 1 if failed else 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (RuntimeError, subprocess.CalledProcessError) as err:
        print(f"bench.reference: error: {err}", file=sys.stderr)
        sys.exit(2)
