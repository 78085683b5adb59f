"""The same fit on CUDA as on the CPU (run by ``make gpu-check``; skipped where torch sees no GPU): a training step's
loss and gradients from the same weights, rays and sample draws, and a short fit that ends finite."""

import pytest
import torch

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def _trainer(capture, device, *sets):
    from fitting.config import load_config
    from fitting.run_folder import prepare_run_dir
    from pipelines.runs.fit import start_run

    config = load_config("cpu", [f"data.subject={capture}", "train.validate_every=0", *sets])
    return start_run(prepare_run_dir(capture.parent / f"run-{device}", True), torch.device(device), config, False)


@cuda
@pytest.mark.parametrize("sets", [(), ("train.pose_correction=true", "train.pose_start=0")])
def test_a_step_gives_the_cpu_loss_and_gradients(tiny_capture, sets):
    """The CPU preset (occupancy grid, grid proposal) on both devices from the same weights and random draws: the loss
    and the gradient agree up to the samples that land elsewhere. Samples are placed by inverse transform of
    cumulative sums of the grid's density, which CUDA rounds in another order, and a sample that crosses a cell or
    box edge (a discrete choice) changes its ray's contribution by a whole step. Measured on an H200: the loss 3e-4
    apart (relative), the gradient 1.7 % of its norm, about evenly over the tensors; the bounds are 2e-3 and 5 %, so a
    wrong kernel (a sign, a transposed rotation), which moves them by tens of percent, fails."""
    from fitting.data import RayBatch
    from fitting.losses import ray_loss

    cpu = _trainer(tiny_capture, "cpu", *sets)
    gpu = _trainer(tiny_capture, "cuda", *sets)
    gpu.field.load_state_dict(cpu.field.state_dict())
    generator = torch.Generator().manual_seed(3)
    t, r = cpu.config.train, cpu.config.render
    batch = cpu.views.sample(t.images_per_step, t.rays_per_image, t.body_fraction, t.border_fraction, generator)
    uniforms = [torch.rand(batch.origins.shape[0], k, generator=generator) for k in (r.train_coarse, r.train_fine)]
    results = []
    for trainer in (cpu, gpu):
        device = trainer.device
        moved = RayBatch(*(getattr(batch, name).to(device) for name in RayBatch.__dataclass_fields__))
        loss, _ = ray_loss(
            trainer.config,
            trainer.field,
            moved,
            trainer.poses_at(),
            None,
            r.train_coarse,
            r.train_fine,
            uniforms=[u.to(device) for u in uniforms],
        )
        trainer.field.zero_grad()
        loss.backward()
        results.append(
            (float(loss), {n: p.grad.cpu() for n, p in trainer.field.named_parameters() if p.grad is not None})
        )
    (loss_cpu, grads_cpu), (loss_gpu, grads_gpu) = results
    a = torch.cat([grads_cpu[n].flatten() for n in grads_cpu])
    b = torch.cat([grads_gpu[n].flatten() for n in grads_cpu])
    assert loss_gpu == pytest.approx(loss_cpu, rel=2e-3)
    assert float((a - b).norm() / a.norm()) < 5e-2


@cuda
def test_a_short_fit_on_cuda_follows_the_cpus(tiny_capture):
    """40 steps of the CPU preset with pose correction on CUDA and on the CPU, same seed: both end finite with a
    checkpoint, and CUDA's loss and correction sizes are the CPU's within 25 % and 50 %. The two fits start from
    the same weights and draws but round differently, and Adam's sign-like first steps grow those differences to
    about 1e-2 of each weight within a few steps (fitting/trainer.py), so the runs are not equal; the size of the
    corrections is set by the loss, not by rounding, and a wrong kernel (a sign, a transposed rotation) moves it by
    far more. Not yet run on a GPU: the bounds are reasoned, not measured."""
    sets = ("train.steps=40", "train.pose_correction=true", "train.pose_start=0")
    results = {}
    for device in ("cpu", "cuda"):
        trainer = _trainer(tiny_capture, device, *sets)
        result = trainer.fit()
        assert result.finished and torch.isfinite(torch.tensor(result.loss))
        assert (trainer.run_dir / "checkpoint.pt").is_file()
        results[device] = (result.loss, trainer.pose_correction.magnitude())
    (loss_cpu, size_cpu), (loss_gpu, size_gpu) = results["cpu"], results["cuda"]
    assert size_cpu["pose_turn_mean_deg"] > 0
    assert loss_gpu == pytest.approx(loss_cpu, rel=0.25)
    assert size_gpu["pose_turn_mean_deg"] == pytest.approx(size_cpu["pose_turn_mean_deg"], rel=0.5)
    assert size_gpu["pose_shift_mean_cm"] == pytest.approx(size_cpu["pose_shift_mean_cm"], rel=0.5)
