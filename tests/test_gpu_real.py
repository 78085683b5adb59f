"""``make gpu-real``'s two halves: the packed capture the fit reads as it reads the original (``pack`` / ``check``),
the steps a side-by-side fit reaches from stage 1's rates, and the run's JSON on the CPU with a tiny budget."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from bench.gpu_real import VARIANTS, check, main, pack, steps_for
from pipelines.datasets.capture import ZjuCapture


def test_a_packed_capture_loads_as_the_original(capture, tmp_path):
    """Every view as the fit loads it: the same masks, and the pixels it keeps (mask, band, undistortion's and
    resize's neighbours) changed only by JPEG at quality 95 (an 8-bit pixel moves a level or two: 40 dB and more
    over the whole image; a band or mask pixel blacked out costs its whole value, which the bound catches). The
    packed images are black beyond the kept region, and the overlay and ``mask/`` stay behind."""
    source = capture / "synthetic" / "taichi"
    packed = tmp_path / "packed"
    pack(source, packed, quality=95, margin=12, drop={"mask", "overlay"})
    assert not (packed / "mask").exists() and (packed / "mask_cihp").is_dir()
    figures = check(source, packed)
    assert figures["masks_equal"] and figures["views"] == 40
    assert figures["full_psnr"] > 40.0 and figures["worst_view_person_psnr"] > 35.0
    image = cv2.imread(str(packed / ZjuCapture(packed).ims[0][0]))
    assert np.mean(image.max(axis=2) < 8) > 0.2  # the background beyond the person and the margin: black


def test_a_pack_that_cuts_into_the_band_is_caught(capture, tmp_path):
    """The same check on a copy blacked out at the mask itself (no band, no margin): the band's pixels lose their
    colour, and the whole-image PSNR falls below the bound above."""
    source = capture / "synthetic" / "taichi"
    packed = tmp_path / "packed"
    pack(source, packed, quality=95, margin=12, drop={"overlay"})
    for row in ZjuCapture(packed).ims:
        for rel in row:
            mask = cv2.imread(str(source / "mask_cihp" / Path(rel).with_suffix(".png")), cv2.IMREAD_GRAYSCALE)
            image = cv2.imread(str(source / rel))
            image[cv2.erode((mask != 0).astype(np.uint8), np.ones((3, 3), np.uint8)) == 0] = 0
            cv2.imwrite(str(packed / rel), image, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert check(source, packed)["full_psnr"] < 40.0


def test_steps_side_by_side_from_the_rates():
    """9,216 rays a step: fp32 at 46,080 rays/s is 0.2 s a step, TF32 at 92,160 is 0.1 s; both side by side cost
    0.3 s a round, so 30 s give 100 steps each."""
    rates = {"fp32": {"rays_per_s": 46_080}, "tf32": {"rays_per_s": 92_160}}
    assert steps_for(rates, ["paper_fp32", "paper_tf32"], 30.0, 9216) == 100
    # a variant without deterministic kernels takes the rate timed with the same suffix, else its precision's
    rates["bf16+nondet"] = {"rays_per_s": 92_160}
    assert steps_for(rates, ["paper_fp32", "paper_bf16_nondet"], 30.0, 9216) == 100
    with pytest.raises(KeyError):
        steps_for({"fp32": {"rays_per_s": 1}}, ["paper_bf16_nondet"], 30.0, 9216)
    rates["bf16"] = {"rays_per_s": 9_216}
    assert steps_for({"bf16": rates["bf16"]}, ["paper_bf16_nondet"], 20.0, 9216) == 20  # 1 s a step
    assert all(any(o.startswith("train.precision=") for o in VARIANTS[name][1]) for name in VARIANTS)


@pytest.mark.slow
def test_the_run_writes_each_stage_on_the_cpu(data_root_64, tmp_path):
    """Stage 1 for a second per precision (fp32 then profiled for 2 steps; bf16 with a suffix's override), then one
    variant for 2 steps and one view a split, on the 64^2 capture with the paper preset shrunk (width 16, 4+4
    samples, 2 x 32 rays): the JSON holds the rates, the profile's named ranges and operators, the budget (the
    steps, capped by --fit-seconds) and the variant's figures from narf-eval."""
    out = tmp_path / "figures.json"
    tiny = ["model.width=16", "render.train_coarse=4", "render.train_fine=4", "render.eval_coarse=4"]
    tiny += ["render.eval_fine=4", "train.images_per_step=2", "train.rays_per_image=32", "data.ratio=1.0"]
    argv = ["run", "--subject", str(data_root_64 / "synthetic" / "taichi"), "--work", str(tmp_path / "work")]
    argv += ["--out", str(out), "--device", "cpu", "--speed-seconds", "1", "--steps", "2", "--limit", "1"]
    argv += ["--variants", "paper_fp32", "--profile", "fp32", "--profile-steps", "2", "--fit-seconds", "600"]
    argv += ["--precisions", "fp32,tf32,bf16+nondet"]
    argv += [a for o in tiny for a in ("--set", o)]
    assert main(argv) == 0
    figures = json.loads(out.read_text())
    assert set(figures["speed"]) == {"fp32", "tf32", "bf16+nondet"}
    assert all(rate["rays_per_s"] > 0 for rate in figures["speed"].values())
    profiled = figures["speed"]["fp32"]["profile"]
    assert "profile" not in figures["speed"]["tf32"] and profiled["steps"] == 2
    assert set(profiled["ranges_cpu_ms_per_step"]) == {"narf.sample", "narf.forward", "narf.backward"}
    assert profiled["top"] and all(row["ms_per_step"] >= 0 for row in profiled["top"])
    assert figures["side_by_side_budget"]["arguments"] == ["--set", "train.steps=2", "--max-minutes", "10.0"]
    fit = figures["side_by_side"]["paper_fp32"]
    assert fit["exit"] == 0 and fit["steps"] == 2
    assert {"same_pose_same_view", "novel_view", "novel_pose"} <= set(fit)


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--variants", "paper_fp16"], "--variants: unknown paper_fp16; known: paper_fp32"),
        (["--speed-seconds", "0"], "--fit-seconds sizes the pose correction's start from stage 1's rates"),
        (["--precisions", "fp32+fast"], "--precisions: fp32+fast is not fp32, tf32 or bf16 with +compile or +nondet"),
        (["--precisions", "tf32", "--variants", "paper_bf16_nondet"], "--variants paper_bf16_nondet: stage 1 timed no"),
    ],
)
def test_bad_arguments_stop_with_one_line_before_any_work(tmp_path, capsys, extra, message):
    """An unknown variant or precision, or a time budget without stage 1's rates, is refused at once: one line,
    exit code 2, and no run folder started."""
    from pipelines.cli.common import run_cli

    argv = ["run", "--subject", str(tmp_path / "capture"), "--work", str(tmp_path / "work"), "--device", "cpu", *extra]
    assert run_cli("python -m bench.gpu_real", main, argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err
    assert not (tmp_path / "work").exists()
