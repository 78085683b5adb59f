"""Bodies that agree with the images (docs/guides/fitting.md, *Pose correction*): the strided skinning against smplx,
the per-knot Adam against torch's, the bodies refined against the masks of a capture whose poses were broken where
the truth is known, the photometric correction with the field held fixed, and ``narf-eval --reference-params``."""

import json

import numpy as np
import pytest
import torch

from pipelines.body.model import BodyModel


def test_strided_vertices_are_smplx_posed_vertices(body_model64):
    """``vertices_zju`` poses every n-th vertex as ``pose_zju`` (smplx's ``lbs``) poses all: float64, the same
    operations in another order, so they agree to a few ulps of metre-sized coordinates."""
    g = torch.Generator().manual_seed(0)
    poses, rh, th = (s * torch.randn(3, n, generator=g, dtype=torch.float64) for s, n in ((0.4, 72), (1, 3), (1, 3)))
    shapes = torch.randn(3, 10, generator=g, dtype=torch.float64)
    for every in (1, 7):
        for blend in (True, False):
            full = body_model64.pose_zju(poses, rh, th, shapes, pose_blendshapes=blend).vertices[:, ::every]
            strided = body_model64.vertices_zju(poses, rh, th, shapes, every, pose_blendshapes=blend)
            torch.testing.assert_close(strided, full, rtol=0, atol=1e-12)


def test_template_offsets_are_skinned_with_the_shapes_skeleton(body_model64):
    """SMPL+D: an offset D added to the rest template moves each posed vertex by its skinned rotation,
    ``sum_i w_i R_i D`` with R_i the rotation of ``pose_zju``'s joint frame i (global rotation included), and leaves
    the skeleton where the shape puts it (an offset in smplx's ``lbs`` template would move the regressed joints).
    float64; the difference of two posings of metre-sized coordinates: a few ulps."""
    g = torch.Generator().manual_seed(1)
    poses, rh, th = (s * torch.randn(2, n, generator=g, dtype=torch.float64) for s, n in ((0.4, 72), (1, 3), (1, 3)))
    shapes = torch.randn(2, 10, generator=g, dtype=torch.float64)
    offsets = 0.02 * torch.randn(body_model64.n_vertices, 3, generator=g, dtype=torch.float64)
    moved = body_model64.vertices_zju(poses, rh, th, shapes, template_offsets=offsets)
    posed = body_model64.pose_zju(poses, rh, th, shapes)
    rotations = posed.world_from_joint[..., :3, :3]  # (B, 24, 3, 3)
    skinned = torch.einsum("vj,bjkl,vl->bvk", body_model64.skinning_weights, rotations, offsets)
    torch.testing.assert_close(moved - posed.vertices, skinned, rtol=0, atol=1e-12)
    worn = body_model64.pose_zju(poses, rh, th, shapes, template_offsets=offsets)
    torch.testing.assert_close(worn.vertices, moved, rtol=0, atol=0)  # the same path
    torch.testing.assert_close(worn.world_from_joint, posed.world_from_joint, rtol=0, atol=0)  # the same skeleton
    normals = body_model64.template_normals
    torch.testing.assert_close(normals.norm(dim=-1), torch.ones(len(normals), dtype=torch.float64))


def test_row_adam_is_adam_per_row():
    """With every row in every step it is torch's Adam (float32: the same formula, within rounding of values of
    order 1 after 20 steps); a row without gradient keeps its value and its moments."""
    from fitting.corrections import RowAdam

    g = torch.Generator().manual_seed(0)
    a = torch.nn.Parameter(torch.randn(5, 3, 2, generator=g))
    b = torch.nn.Parameter(a.detach().clone())
    reference, rows = torch.optim.Adam([a], lr=0.01, eps=1e-12), RowAdam([b], lr=0.01)
    for _ in range(20):
        gradient = torch.randn(5, 3, 2, generator=g)
        a.grad, b.grad = gradient.clone(), gradient.clone()
        reference.step()
        rows.step()
    torch.testing.assert_close(b, a, rtol=0, atol=1e-5)
    before = b.detach().clone()
    moments = rows.state[b]["exp_avg"].clone()
    b.grad = torch.zeros_like(b)
    b.grad[2] = 1.0
    rows.step()
    untouched = [0, 1, 3, 4]
    assert torch.equal(b.detach()[untouched], before[untouched]) and not torch.equal(b.detach()[2], before[2])
    assert torch.equal(rows.state[b]["exp_avg"][untouched], moments[untouched])
    assert rows.state[b]["step"].tolist() == [20, 20, 21, 20, 20]


@pytest.fixture(scope="session")
def perturbed(tiny_capture, tmp_path_factory):
    """The 256^2 tiny capture with every joint turned 4 degrees and the body moved 2 cm (``narf-synth --degrade``),
    trained on three of its four cameras (its own splits train on one, from which a silhouette cannot tell depth)."""
    from pipelines.synthetic.degrade import Degradation, degrade_capture

    out = tmp_path_factory.mktemp("perturbed") / "taichi_pose4"
    degrade_capture(tiny_capture, out, Degradation(pose_degrees=4.0, shift_m=0.02), progress=False)
    split = {"train_frames": [0, 1, 2], "novel_frames": [3], "train_views": [0, 1, 2], "test_views": [3]}
    (out / "splits.json").unlink(missing_ok=True)  # never write through a hard link to the source's file
    (out / "splits.json").write_text(json.dumps(split))
    return out


def _joint_error(truth, source, frames) -> float:
    from pipelines.datasets.capture import ZjuCapture
    from pipelines.synthetic.degrade import joint_errors

    return 100 * float(joint_errors(ZjuCapture(truth), source, BodyModel(), frames).mean())


def test_bodies_refined_against_the_masks_find_the_truth(tiny_capture, perturbed):
    """The refinement brings 4-degree, 2-cm bodies to under half their joint error against the truth from three
    cameras' masks at 128 px (measured 4.29 -> 1.00 cm on this capture; the 270-frame synthetic capture at 256 px:
    4.73 -> 0.74 cm)."""
    from fitting.config import load_config
    from pipelines.runs.subject.body_refine import RefinedCapture, RefineSettings, refine_to_masks
    from pipelines.runs.subject.session import build_fit_data, open_capture

    sets = [f"data.subject={perturbed}", "train.pose_correction=true", "train.mask_body_iterations=0"]
    config = load_config("tiny", sets)
    data = build_fit_data(config, "cpu", progress=False)
    capture = open_capture(config, quiet=True)
    refined = refine_to_masks(data.training, capture, BodyModel(), data.frames, RefineSettings(progress=False))
    before = _joint_error(tiny_capture, capture, data.frames)
    after = _joint_error(tiny_capture, RefinedCapture(capture, refined), data.frames)
    assert before > 3.0 and after < 0.5 * before, (before, after)


def test_eval_reports_joint_errors_against_reference_params(tiny_capture, perturbed, tmp_path, capsys):
    """``narf-eval --reference-params``: the run's (refined) training poses against the truth, beside the capture's
    own; a folder that is not there is one line, exit 2."""
    from fitting.config import load_config
    from fitting.run_folder import prepare_run_dir
    from pipelines.cli.eval import entrypoint, main
    from pipelines.runs.fit import start_run

    config = load_config("tiny", [f"data.subject={perturbed}", "train.pose_correction=true", "train.steps=2"])
    start_run(prepare_run_dir(tmp_path / "run", False), torch.device("cpu"), config, progress=False).fit()
    assert main(["--run", str(tmp_path / "run"), "--reference-params", str(tiny_capture / "new_params")]) == 0
    report = json.loads((tmp_path / "run" / "eval" / "joints.json").read_text())
    assert report["corrected"] and report["frames"] > 0
    assert report["run_joint_error_cm"] < 0.5 * report["capture_joint_error_cm"], report
    assert "joint error against" in capsys.readouterr().out
    with pytest.raises(SystemExit) as stop:
        import sys

        sys.argv = ["narf-eval", "--run", str(tmp_path / "run"), "--reference-params", str(tmp_path / "nowhere")]
        entrypoint()
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nowhere: no such params folder" in err[0]


def test_refined_params_pose_as_recorded(perturbed):
    """The refined bodies keep the capture's shapes and its zero ``poses[:3]`` (the global turn is Rh)."""
    from fitting.config import load_config
    from pipelines.runs.subject.body_refine import RefineSettings, refine_to_masks
    from pipelines.runs.subject.session import build_fit_data, open_capture

    config = load_config(
        "tiny", [f"data.subject={perturbed}", "train.pose_correction=true", "train.mask_body_iterations=0"]
    )
    data = build_fit_data(config, "cpu", progress=False)
    capture = open_capture(config, quiet=True)
    refined = refine_to_masks(
        data.training, capture, BodyModel(), data.frames, RefineSettings(iterations=5, progress=False)
    )
    for frame, params in refined.items():
        assert np.array_equal(params.shapes, capture.params(frame).shapes)
        assert np.array_equal(params.poses[:3], capture.params(frame).poses[:3])


# session-scoped, as ``perturbed``: a module's fixtures are torn down whenever its worker runs another module's
# test in between, so the xdist group alone does not keep one fitted field for both tests below
@pytest.fixture(scope="session")
def exact_field(tiny_capture, tmp_path_factory):
    """A field fitted for 300 steps of the CPU preset on the tiny capture's exact poses, trained on the same three
    cameras as ``perturbed``."""
    from fitting.config import load_config
    from fitting.run_folder import prepare_run_dir
    from pipelines.runs.fit import start_run
    from pipelines.synthetic.degrade import Degradation, degrade_capture

    root = tmp_path_factory.mktemp("exact")
    exact = degrade_capture(tiny_capture, root / "taichi", Degradation(pose_degrees=0.0, shift_m=0.0), progress=False)
    split = {"train_frames": [0, 1, 2], "novel_frames": [3], "train_views": [0, 1, 2], "test_views": [3]}
    (exact / "splits.json").unlink(missing_ok=True)
    (exact / "splits.json").write_text(json.dumps(split))
    # without the preset's left-right symmetry, with its earlier 64 rays an image and rate 0.01: the pose correction's
    # figures below were measured on this field
    sets = [f"data.subject={exact}", "train.steps=300", "train.mask_body_iterations=0", "train.validate_every=0"]
    sets += ["train.mirror_weight=0", "train.rays_per_image=64", "train.lr=0.01"]
    start_run(prepare_run_dir(root / "run", False), torch.device("cpu"), load_config("cpu", sets), False).fit()
    return root / "run"


@pytest.mark.slow
@pytest.mark.xdist_group("exact_field")  # one worker fits the field for both (make test: --dist loadgroup)
def test_the_photometric_gradient_points_to_the_true_poses(exact_field, perturbed):
    """With the field fixed, the loss's gradient with respect to the pose corrections points towards the true poses
    (the negated noise of ``narf-synth --degrade``), as a central finite difference along that direction does, and
    the true poses have the lower loss. A gradient path to the pose that is cut (slope 0) or reversed fails here.

    The two slopes do not agree in size, and need not: the finite difference over +-5 % of the noise (0.2 degrees)
    averages a loss that is rough over the pose at the scale of 1e-4 rad (the point encoding's top frequencies), and
    the gradient passes through the encoding's four lowest frequencies only (``train.pose_gradient_freqs``). With
    the samples held in place and every frequency passing, the gradient matches central differences of 3e-5 to
    1e-5 rad (docs/results/real-capture.md). So the bounds are signs, and signs are what fail: a cut path gives a
    slope of exactly 0, a reversed one a positive slope, and a field that did not learn the exact poses a truth no
    better than the start."""
    from fitting.losses import ray_loss
    from pipelines.runs.subject.pose_check import field_fixed_trainer
    from pipelines.synthetic.degrade import Degradation, pose_noise

    with field_fixed_trainer(exact_field, perturbed, ["train.mask_body_iterations=0"]) as trainer:
        correction, t, r = trainer.pose_correction, trainer.config.train, trainer.config.render
        frames = [int(f) for f in trainer.frames]
        truth = [-v[frames].float() for v in pose_noise(4, Degradation(pose_degrees=4.0, shift_m=0.02))]
        generator = torch.Generator().manual_seed(0)
        batch = trainer.views.sample(len(trainer.views), 512, t.body_fraction, t.border_fraction, generator)
        uniforms = [torch.rand(batch.origins.shape[0], k, generator=generator) for k in (r.train_coarse, r.train_fine)]
        parameters = (correction.joints, correction.root, correction.shift)

        def loss(scale: float) -> torch.Tensor:
            with torch.no_grad():
                for parameter, value in zip(parameters, truth):
                    parameter.copy_(scale * value)
            args = (trainer.config, trainer.field, batch, trainer.poses_at(), None, r.train_coarse, r.train_fine)
            return ray_loss(*args, uniforms=uniforms, randomized=True)[0]

        at_zero = loss(0.0)
        at_zero.backward()
        at_zero = float(at_zero.detach())
        slope = float(sum((p.grad * v).sum() for p, v in zip(parameters, truth)))
        step = 0.05
        with torch.no_grad():
            difference = (float(loss(step)) - float(loss(-step))) / (2 * step)
            at_truth = float(loss(1.0))
    assert slope < 0 and difference < 0, (slope, difference)
    assert at_truth < at_zero, (at_truth, at_zero)


@pytest.mark.slow
@pytest.mark.xdist_group("exact_field")  # one worker fits the field for both (make test: --dist loadgroup)
def test_the_photometric_correction_recovers_the_poses_with_the_field_fixed(exact_field, perturbed, tiny_capture):
    """The fit's own correction (rays, loss, per-knot Adam, prior, the band-limited pose gradient) with the field held
    fixed brings the 4-degree, 2-cm poses of three frames a third of the way back in 300 steps (measured 4.60 ->
    2.83 cm, 38 %; the 27-frame synthetic benchmark recovers 84 %). Through every frequency of the point encoding it
    does not converge (4.29 -> 5.9 cm on a field of 400 steps, -38 %), and a cut gradient path recovers nothing
    (0 %). The bound, 25 %, lies between those failures (<= 0 %) and the measured 38 %: it leaves a third of the
    measured recovery for what differs between machines (float32 summation order differs between CPUs, and Adam's
    steps amplify it), and still fails both broken paths by 25 points."""
    from pipelines.runs.subject.pose_check import PoseCheckRequest, correct_with_field_fixed

    request = PoseCheckRequest(exact_field, perturbed, tiny_capture, 300, ("train.mask_body_iterations=0",), 100)
    check = correct_with_field_fixed(request)
    assert check.recovered > 0.25, check.path
