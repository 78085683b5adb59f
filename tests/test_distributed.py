"""Data-parallel fitting under torchrun: 2 CPU processes (gloo) follow the single-process fit with the same global
batch, record their world size, write one checkpoint, and resume."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from fitting.checkpoint import load_checkpoint
from fitting.distributed import Processes

ROOT = Path(__file__).resolve().parents[1]


def test_shares_cover_the_batch_once():
    for n in (7, 8, 64):
        for world in (1, 2, 3):
            covered = [i for rank in range(world) for i in range(n)[Processes(rank, world).share(n)]]
            assert covered == list(range(n))


def _fit(args: list[str], processes: int) -> None:
    launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={processes}"]
    command = [*(launcher if processes > 1 else [sys.executable]), "-m", "pipelines.cli.fit", *args]
    done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]


@pytest.mark.slow
def test_two_processes_follow_one(data_root_64, tmp_path):
    common = ["--config", "tiny", "--data-root", str(data_root_64), "--set", "data.ratio=1.0", "--quiet"]
    _fit([*common, "--set", "train.steps=5", "--out", str(tmp_path / "one")], 1)
    _fit([*common, "--set", "train.steps=3", "--out", str(tmp_path / "two")], 2)
    _fit(["--out", str(tmp_path / "two"), "--resume", "--set", "train.steps=5", "--quiet"], 2)
    one, two = load_checkpoint(tmp_path / "one"), load_checkpoint(tmp_path / "two")
    assert one["step"] == two["step"] == 5 and two["config"]["train"]["world_size"] == 2
    rows = [json.loads(line) for line in (tmp_path / "two" / "log.jsonl").read_text().splitlines()]
    assert rows and all(row["world_size"] == 2 for row in rows)
    assert "world_size: 2" in (tmp_path / "two" / "config.yaml").read_text()
    assert not list((tmp_path / "two").glob(".checkpoint.*.tmp"))
    # Adam's first moments are 0.1-weighted sums of the gradients: the summed shares equal the single-process
    # gradient up to float32 summation order (~1e-7 relative of moments up to ~0.05); halved (averaged) or
    # missing shares would be off by half the moment
    for key, state in one["optimizer"]["state"].items():
        torch.testing.assert_close(two["optimizer"]["state"][key]["exp_avg"], state["exp_avg"], atol=1e-6, rtol=0)
    # the weights: Adam (eps 1e-12) divides each moment by its own running magnitude, so the few weights whose
    # gradient sits at the rounding level can take a different step of up to ~lr = 0.01 (at most 2 lr per step,
    # 0.1 over 5 steps); all others agree to float32 rounding of O(1) weights after 5 steps
    diff = torch.cat(
        [(two["model"][k] - v).abs().reshape(-1) for k, v in one["model"].items() if v.is_floating_point()]
    )
    assert diff.max() < 0.1 and torch.quantile(diff, 0.99) < 1e-5
