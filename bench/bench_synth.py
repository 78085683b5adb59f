"""Time and size of generating the default synthetic ``taichi`` capture."""

from __future__ import annotations

import resource
import shutil
import tempfile
import time
from pathlib import Path

from pipelines.synthetic.capture import SynthConfig, generate_capture


def run(resolution: int = 512) -> list[dict]:
    config = SynthConfig(resolution=resolution)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "taichi"
        start = time.perf_counter()
        generate_capture(out, config, progress=False)
        seconds = time.perf_counter() - start
        size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file()) / 1e6
        shutil.rmtree(out)
    usage = resource.getrusage
    peak = max(usage(resource.RUSAGE_SELF).ru_maxrss, usage(resource.RUSAGE_CHILDREN).ru_maxrss)
    setting = (
        f"{config.frames} frames x {config.cameras} cams, {resolution}^2, {config.calib_shots} calib shots + "
        f"{config.calib_close_ups} close-ups per camera"
    )
    return [
        {
            "benchmark": "narf-synth taichi",
            "setting": setting,
            "value": f"{seconds:.0f} s, {size:.0f} MB",
            "peak RSS": f"{peak / 1024:.0f} MB",
        }
    ]
