"""Training and rendering speed of every model at paper size and at the CPU default size.

Each configuration runs in its own process (so peak RSS is per configuration) on real stand-in poses: the
taichi motion posed through the body model, part boxes fitted as in docs/model.md, rays from a ring camera aimed at
the body (only rays that hit a box are counted, as in training). A "train step" is the full step: coarse pass,
importance sampling, final pass with gradient, colour + mask loss, backward and Adam.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

from pipelines.datasets.smpl_files import command_environment

#: (row label, model, constructor kwargs, train (Nc, Nf), render (Nc, Nf), rays per train step)
CONFIGS = [
    ("NARF_D width 64", "narf_d", {"width": 64}, (16, 16), (16, 16), 1024),
    ("NARF_D paper", "narf_d", {"width": 256}, (48, 48), (64, 128), 256),
    ("NARF_D width 64 dense reference", "narf_d", {"width": 64, "fast": False}, (16, 16), (16, 16), 1024),
    ("NARF_D width 64, torch.compile", "narf_d", {"width": 64, "compile": True}, (16, 16), (16, 16), 1024),
    ("NARF_H width 64", "narf_h", {"width": 64}, (16, 16), (16, 16), 1024),
    ("NARF_H paper", "narf_h", {"width": 256}, (48, 48), (64, 128), 256),
    ("NARF_P width 32", "narf_p", {"width": 32}, (16, 16), (16, 16), 1024),
    ("NARF_P width 32 dense reference", "narf_p", {"width": 32, "fast": False}, (16, 16), (16, 16), 256),
    ("NARF_P paper (256)", "narf_p", {"width": 256}, (48, 48), (64, 128), 32),
    ("P-NeRF width 64", "p_nerf", {"width": 64}, (16, 16), (16, 16), 1024),
    ("P-NeRF paper", "p_nerf", {"width": 256}, (48, 48), (64, 128), 256),
    ("D-NARF width 64", "d_narf", {"width": 64}, (16, 16), (16, 16), 1024),
    ("D-NARF width 64 dense reference", "d_narf", {"width": 64, "fast": False}, (16, 16), (16, 16), 1024),
    ("D-NARF paper", "d_narf", {"width": 256}, (48, 48), (64, 128), 256),
]
RENDER_SIZE = 256
RENDER_RAY_BUDGET = 4096  # rays rendered for timing; the full-frame time is extrapolated from hit rays


def _scene():
    import numpy as np
    import torch

    from narf.rays import image_pixels, ray_box_intersect, rays_from_pixels
    from pipelines.body.model import BodyModel, pose_batch
    from pipelines.synthetic.scene import look_at, taichi_motion

    body_model = BodyModel()
    motion = taichi_motion(8, seed=0)
    args = [torch.as_tensor(motion[k], dtype=torch.float32) for k in ("poses", "Rh", "Th", "shapes")]
    args[2] = args[2] + torch.tensor([0.0, 0.0, -1.0])
    with torch.no_grad():
        bodies = body_model.pose_zju(*args)
    centres, half = body_model.part_boxes([body_model.rest_body(args[3][:1]), bodies])
    cam_from_world = torch.as_tensor(
        look_at(np.array([0.0, -3.0, -1.9]), np.array([0.0, 0.0, -0.9])), dtype=torch.float32
    )
    focal = 1100 * RENDER_SIZE / 1024
    K = torch.tensor([[focal, 0, RENDER_SIZE / 2], [0, focal, RENDER_SIZE / 2], [0, 0, 1.0]])
    origins, dirs = rays_from_pixels(K, cam_from_world, image_pixels(RENDER_SIZE, RENDER_SIZE))
    pose = pose_batch(bodies)
    frames = torch.zeros(origins.shape[0], dtype=torch.long)
    per_ray = pose.select(frames)
    near, far, hit = ray_box_intersect(origins, dirs, per_ray.world_from_part, per_ray.reach, centres, half)
    return pose, centres, half, origins[hit], dirs[hit], near[hit], far[hit], int(hit.sum())


def matmul_gflops(size: int = 2048, repeats: int = 5) -> float:
    """The machine's fp32 matrix-multiply rate (GFLOP/s, 2 n^3 per product, best of ``repeats``), so that figures
    from different machines can be compared (the share of it a training step reaches is a column)."""
    import torch

    torch.set_num_threads(2)
    a, b = torch.randn(size, size), torch.randn(size, size)
    a @ b  # warm-up
    best = min(_timed(lambda: a @ b) for _ in range(repeats))
    return 2 * size**3 / best / 1e9


def _timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def train_flops_per_ray(field, n_coarse: int, n_fine: int) -> float:
    """Nominal FLOPs of one training ray: a forward pass over the coarse samples (no gradient), then forward and
    backward (about twice the forward) over all samples; per-sample FLOPs from the field's complete cost
    (docs/model.md), i.e. of the dense formulation: a sparse fast path does less work than this counts."""
    from narf.fields.base import SAMPLES_FOR_COST

    per_sample = field.cost().flops_per_ray_complete / SAMPLES_FOR_COST
    return per_sample * (n_coarse + 3 * (n_coarse + n_fine))


def _measure(index: int) -> dict:
    import resource

    import torch

    from narf.fields import build_field
    from pipelines.cli.common import flush_subnormals, keep_freed_memory

    flush_subnormals()  # before any parallel work, as the commands do (docs/design.md, "Subnormal numbers")
    keep_freed_memory()  # as the commands run (docs/design.md, "Memory allocator")
    torch.set_num_threads(2)
    label, name, kwargs, (n_c, n_f), (r_c, r_f), n_rays = CONFIGS[index]
    scene = _scene()
    kwargs = dict(kwargs)
    compiled = kwargs.pop("compile", False)
    field = build_field(name, **kwargs)
    field.set_boxes(scene[1], scene[2])
    if compiled:  # as train.compile does; the first steps (compilation) are not timed
        field.forward = torch.compile(field.forward, dynamic=True)
    result = {
        "model": label,
        "params": f"{sum(p.numel() for p in field.parameters()) / 1e6:.2f}M",
        "samples/ray train": n_c + n_f,
    }
    for precision in ("fp32",) if compiled else ("fp32", "bf16"):
        steps = (2, 6) if compiled else (1, 3)  # (untimed, timed): compilation takes the first two
        rate = _train_rate(field, scene, n_c, n_f, n_rays, precision, *steps)
        result[f"train rays/s {precision}"] = f"{rate:,.0f}"
        result[f"train samples/s {precision}"] = f"{rate * (n_c + n_f):,.0f}"
        if precision == "fp32":
            share = rate * train_flops_per_ray(field, n_c, n_f) / (matmul_gflops() * 1e9)
            result["nominal FLOP/s share of fp32 matmul"] = f"{100 * share:.1f} %"
    if not compiled:  # rendering would compile the no-gradient graphs again; timed for the eager rows only
        heavy = kwargs.get("width", 64) * (19 if name == "narf_p" else 1) * (r_c + r_f)
        seconds, estimated = _render_seconds(field, scene, heavy, r_c, r_f)
        result["render samples"] = f"{r_c}+{r_f}"
        result[f"render {RENDER_SIZE}^2 s"] = f"{seconds:.1f}{' (est.)' if estimated else ''}"
    result["peak RSS MB"] = f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f}"
    return result


def _train_rate(field, scene, n_c: int, n_f: int, n_rays: int, precision: str, warm_up: int, timed: int) -> float:
    """Training rays a second: the mean of ``timed`` Adam steps (rendering, loss, backward, update) after
    ``warm_up`` untimed ones."""
    import torch

    from narf.renderer import bind_field, render_rays

    pose, _, _, origins, dirs, near, far, _ = scene
    optimiser = torch.optim.Adam(field.parameters(), lr=1e-3)
    gen = torch.Generator().manual_seed(0)
    times = []
    for step in range(warm_up + timed):
        pick = torch.randint(0, origins.shape[0], (n_rays,), generator=gen)
        frames = torch.randint(0, pose.reach.shape[0], (n_rays,), generator=gen)
        start = time.perf_counter()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16"):
            out = render_rays(
                bind_field(field, dirs[pick], pose, frames),
                origins[pick],
                dirs[pick],
                near[pick],
                far[pick],
                torch.ones(n_rays, dtype=torch.bool),
                n_c,
                n_f,
                generator=gen,
            )
            loss = (out.rgb.float() - 0.5).pow(2).mean() + (out.mask.float() - 1).pow(2).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        if step >= warm_up:
            times.append(time.perf_counter() - start)
    return n_rays / (sum(times) / len(times))


def _render_seconds(field, scene, heavy: int, r_c: int, r_f: int) -> tuple[float, bool]:
    """Seconds to render the scene's body rays at evaluation settings, as ``render_image`` does (the coarse outputs
    reused), in chunks bounded by ``heavy`` (width x samples); a heavy model renders a share of the rays and the
    time is scaled to all of them (then the flag is true)."""
    import torch

    from narf.renderer import bind_field, render_rays_inference

    pose, _, _, origins, dirs, near, far, n_hit = scene
    chunk_rays = max(32, min(4096, (4096 * 64 * 32) // heavy))  # bounded activation memory per chunk
    budget = min(RENDER_RAY_BUDGET if heavy <= 64 * 64 else 4 * chunk_rays, n_hit)
    frames = torch.zeros(budget, dtype=torch.long)

    def render(sl: slice) -> None:
        hit = torch.ones(sl.stop - sl.start, dtype=torch.bool)
        bound = bind_field(field, dirs[sl], pose, frames[sl])
        render_rays_inference(bound, origins[sl], dirs[sl], near[sl], far[sl], hit, r_c, r_f)

    with torch.no_grad():
        render(slice(0, 64))  # warm-up call (first no-grad shapes)
        start = time.perf_counter()
        for chunk in range(0, budget, chunk_rays):
            render(slice(chunk, min(chunk + chunk_rays, budget)))
    return (time.perf_counter() - start) * n_hit / budget, budget != n_hit


def machine() -> str:
    """CPU model, logical cores, torch version."""
    import platform

    import torch

    name = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as handle:
            name = next(line.split(":", 1)[1].strip() for line in handle if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{name}, {os.cpu_count()} logical cores, torch {torch.__version__}"


def run() -> list[dict]:
    rows = [{"model": f"(machine: {machine()}; fp32 matmul {matmul_gflops():.0f} GFLOP/s on 2 threads, 2048^2)"}]
    for index in range(len(CONFIGS)):
        code = f"import json, bench.bench_models as b; print(json.dumps(b._measure({index})))"
        command = [sys.executable, "-c", code]
        done = subprocess.run(command, capture_output=True, text=True, env=command_environment())
        if done.returncode != 0:
            lines = done.stderr.strip().splitlines()
            reason = lines[-1] if lines else f"killed by signal {-done.returncode}"
            rows.append({"model": CONFIGS[index][0], "params": f"failed: {reason}"})
            continue
        rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    return rows
