"""Each camera's colour gain measured on the floor (pipelines/prepare/layout/colour.py), its file (colour.json) and its
use in the fit's loss and in evaluation (docs/model.md §6, *Measured camera colour*)."""

import json
import shutil
from unittest import mock

import cv2
import numpy as np
import pytest
import torch

from fitting.corrections import CameraColour, MeasuredColour, camera_response
from fitting.losses import batch_loss
from pipelines.datasets.camera import Camera
from pipelines.datasets.camera_colour import read_camera_colour, write_camera_colour
from pipelines.datasets.errors import CaptureError
from pipelines.prepare.layout.colour import background_image, floor_colours, floor_grid, solve_gains
from pipelines.synthetic.scene import look_at

#: BGR gains of the three test cameras (a white balance and exposure spread of about 10 %)
GAINS_BGR = np.array([[1.10, 0.95, 1.00], [0.90, 1.05, 1.10], [1.00, 1.00, 0.92]])


def _cameras() -> list[Camera]:
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    cameras = []
    for i, azimuth in enumerate(np.radians([0, 120, 240])):
        centre = np.array([3 * np.cos(azimuth), 3 * np.sin(azimuth), 2.0])
        dist = np.array([-0.1, 0, 0, 0, 0]) if i == 1 else np.zeros(5)  # one camera with radial distortion
        cameras.append(Camera(f"cam{i}", K, dist, look_at(centre, np.zeros(3), down=(0.0, 0.0, -1.0)), 320, 240))
    return cameras


def _texture(points: np.ndarray) -> np.ndarray:
    """A smooth floor colour (BGR, 55-185): at most about 1 level per cm, so nearest-pixel sampling moves little."""
    x, y = points[:, 0], points[:, 1]
    return np.stack(
        [120 + 40 * np.sin(1.5 * x) + 20 * np.cos(y), 110 + 30 * np.cos(1.2 * y), 130 + 45 * np.sin(x + y)], 1
    )


def _floor_view(camera: Camera, gain_bgr: np.ndarray) -> np.ndarray:
    """The camera's image of the textured floor z = 0 through its gains (uint8 BGR), found by casting each pixel's
    ray (OpenCV's undistortPoints inverts the distortion) onto the floor."""
    ys, xs = np.mgrid[: camera.height, : camera.width]
    pixels = np.stack([xs, ys], -1).reshape(-1, 1, 2).astype(np.float64)
    normalised = cv2.undistortPoints(pixels, camera.K, camera.dist).reshape(-1, 2)
    dirs = np.c_[normalised, np.ones(len(normalised))] @ camera.cam_from_world[:3, :3]  # R^T d, row-wise
    along = -camera.centre[2] / dirs[:, 2]
    colour = _texture(camera.centre + along[:, None] * dirs) * gain_bgr
    colour[along <= 0] = 0
    return np.clip(np.rint(colour), 0, 255).astype(np.uint8).reshape(camera.height, camera.width, 3)


def _measured(cameras, views_of):
    backgrounds, scales = zip(*(background_image(views_of(c, camera)) for c, camera in enumerate(cameras)))
    points = floor_grid(np.array([0.0, 0.0, 1.0]), 0.0, np.zeros((1, 3)), 1.0, 0.04)
    return solve_gains(floor_colours(list(backgrounds), list(scales), cameras, points))


def test_gains_of_cameras_looking_at_a_textured_floor_are_recovered():
    """Three cameras see one textured floor through known gains, with a person walking through each view (masked)
    and a static box that only one camera sees (not masked). The gains come back in RGB, their geometric mean 1,
    within 1 %: uint8 rounding of colours 55-185 is at most 0.9 % of one pixel, and the median over thousands of
    points is far closer; the box's points are outliers the pair medians ignore."""
    cameras = _cameras()
    rng = np.random.default_rng(0)

    def views_of(c, camera):
        floor = _floor_view(camera, GAINS_BGR[c])
        for step in range(5):  # a person walks across: random colours inside the mask
            image, person = floor.copy(), np.zeros(floor.shape[:2], bool)
            person[60:200, 40 + 50 * step : 90 + 50 * step] = True
            image[person] = rng.integers(0, 256, (int(person.sum()), 3))
            if c == 0:
                image[150:200, 200:260] = (30, 200, 90)  # a box on the floor, seen by this camera only
            yield image, person

    result = _measured(cameras, views_of)
    expected = GAINS_BGR[:, ::-1] / np.exp(np.log(GAINS_BGR[:, ::-1]).mean(0))
    np.testing.assert_allclose(result["gains"], expected, rtol=0.01)
    assert result["measured"].all() and (result["points"] > 500).all()
    assert np.exp(np.log(result["gains"]).mean(0)) == pytest.approx([1, 1, 1], abs=1e-9)  # least squares, exact


def test_the_background_is_the_scene_without_the_person():
    """A person who stands in one place for 3 of 5 views and then walks on: where they stood, the background is the
    floor (to the colour's rounding), and where they stood in every view it is unknown (NaN)."""
    camera = _cameras()[0]
    floor = _floor_view(camera, GAINS_BGR[0])
    rng = np.random.default_rng(2)
    views, always = [], np.zeros(floor.shape[:2], bool)
    always[10:30, 10:30] = True
    for step in range(5):
        image, person = floor.copy(), always.copy()
        person[60:200, 40 + 60 * max(0, step - 2) : 90 + 60 * max(0, step - 2)] = True
        image[person] = rng.integers(0, 256, (int(person.sum()), 3))
        views.append((image, person))
    background, scale = background_image(iter(views))
    assert scale == 1.0 and np.isnan(background[15, 15]).all()
    stood = np.zeros_like(always)
    stood[80:180, 60:70] = True  # the person's place in views 0-2, away from the dilated edge
    np.testing.assert_allclose(background[stood], floor[stood], atol=0.5)  # a median of equal uint8 values


def test_a_camera_that_shares_no_floor_keeps_the_gain_one():
    colours = np.full((3, 200, 3), np.nan)
    colours[0, :100], colours[1, :100] = 100.0, 120.0  # cameras 0 and 1 share 100 points; camera 2 sees none
    result = solve_gains(colours)
    assert result["measured"].tolist() == [True, True, False]
    np.testing.assert_allclose(result["gains"][2], 1.0)
    np.testing.assert_allclose(result["gains"][1] / result["gains"][0], 1.2)  # 120 / 100, every channel
    assert result["points"].tolist() == [100, 100, 0]


def test_groups_that_share_no_floor_measure_only_the_largest():
    """Cameras 0-2 share the floor, cameras 3-4 share it with each other only: the gain between the two groups is
    not determined, so the smaller group keeps the gain 1 and is reported unmeasured. (Checked against the solve of
    every linked camera: cameras 3 and 4 were reported measured.)"""
    colours = np.full((5, 300, 3), np.nan)
    colours[0, :100], colours[1, :100], colours[2, :100] = 100.0, 110.0, 121.0
    colours[3, 200:], colours[4, 200:] = 90.0, 180.0
    result = solve_gains(colours)
    assert result["measured"].tolist() == [True, True, True, False, False]
    np.testing.assert_allclose(result["gains"][3:], 1.0)
    np.testing.assert_allclose(result["gains"][1] / result["gains"][0], 1.1)  # every channel, float64 logs


def test_a_gain_a_fit_would_refuse_is_left_unmeasured_and_never_written(tmp_path):
    """A camera whose floor reads 20 times brighter (a measurement gone wrong: a fit refuses gains outside [0.25, 4])
    is left out, the rest solved without it; writing such a gain is refused. (Checked against the solve without the
    range: camera 2 got a gain of 7.2 and the file was written, then refused by the reader.)"""
    from pipelines.datasets.camera_colour import read_camera_colour, write_camera_colour

    colours = np.full((3, 100, 3), 100.0)
    colours[1] *= 1.05
    colours[2] *= 20.0
    result = solve_gains(colours)
    assert result["measured"].tolist() == [True, True, False]
    np.testing.assert_allclose(result["gains"][2], 1.0)
    np.testing.assert_allclose(result["gains"][1] / result["gains"][0], 1.05)
    write_camera_colour(tmp_path / "colour.json", ["a", "b", "c"], result)
    assert read_camera_colour(tmp_path / "colour.json", ["a", "b", "c"]).shape == (3, 3)
    with pytest.raises(ValueError, match="outside"):
        write_camera_colour(tmp_path / "bad.json", ["a", "b", "c"], {**result, "gains": result["gains"] * 5})
    assert not (tmp_path / "bad.json").exists()


def test_pair_medians_ignore_a_minority_of_outliers():
    """The median of a pair's log ratios is exactly the true ratio while more than half the points agree."""
    rng = np.random.default_rng(1)
    floor = rng.uniform(40, 200, (400, 3))
    colours = np.stack([floor * 0.9, floor * 1.0, floor * 1.2])
    colours[2, :150] = rng.uniform(20, 240, (150, 3))  # 37 % of camera 2's points are not the floor
    result = solve_gains(colours)
    expected = np.array([0.9, 1.0, 1.2]) / np.exp(np.log([0.9, 1.0, 1.2]).mean())
    np.testing.assert_allclose(result["gains"][:, 0], expected, rtol=1e-6)  # float64 logs and a 3 x 3 solve


def test_colour_file_round_trip_and_bad_files_are_named(tmp_path):
    names = ["cam01", "cam02"]
    measured = {
        "method": "floor",
        "gains": np.array([[0.9, 1.0, 1.1], [1.1, 1.0, 0.9]]),
        "points": np.array([10, 12]),
        "residual": np.array([0.01, 0.02]),
        "measured": np.array([True, True]),
    }
    path = tmp_path / "colour.json"
    write_camera_colour(path, names, measured)
    np.testing.assert_allclose(read_camera_colour(path, names), measured["gains"], rtol=1e-6)  # 5 decimals kept
    with pytest.raises(CaptureError, match="colour.json.*missing"):
        read_camera_colour(path, [*names, "cam03"])
    with pytest.raises(CaptureError, match="colour.json.*not the capture"):
        read_camera_colour(path, ["cam01"])
    data = json.loads(path.read_text())
    data["cameras"]["cam02"]["gain"] = [1.0, -1.0, 1.0]
    path.write_text(json.dumps(data))
    with pytest.raises(CaptureError, match="colour.json: cam02's gain"):
        read_camera_colour(path, names)
    path.write_text("{not json")
    with pytest.raises(CaptureError, match="colour.json: not a colour file"):
        read_camera_colour(path, names)


def test_camera_response_scales_the_person_not_the_background():
    """C' = g (C - (1 - M) bg) + (1 - M) bg, by hand: a half-covered pixel on white."""
    rgb = torch.tensor([[0.2 * 0.5 + 0.5, 0.4 * 0.5 + 0.5, 0.5]])  # colour (0.2, 0.4, 0) at M = 0.5 on white
    got = camera_response(rgb, torch.tensor([0.5]), torch.tensor([2.0, 0.5, 1.0]), 1.0)
    torch.testing.assert_close(got, torch.tensor([[0.2 + 0.5, 0.1 + 0.5, 0.5]]))


def test_measured_gains_come_before_the_learned_transform():
    measured = MeasuredColour(torch.tensor([[2.0, 2.0, 2.0], [1.0, 0.5, 1.0]]))
    rgb, opacity, cameras = torch.tensor([[0.1, 0.2, 0.3], [0.4, 0.4, 0.4]]), torch.ones(2), torch.tensor([0, 1])
    torch.testing.assert_close(measured(rgb, opacity, cameras), torch.tensor([[0.2, 0.4, 0.6], [0.4, 0.2, 0.4]]))
    learned = CameraColour(2)
    with torch.no_grad():
        learned.offset.copy_(torch.tensor([[0.1, 0, 0], [-0.1, 0, 0]]))
    both = MeasuredColour(measured.gains, learned)
    torch.testing.assert_close(both(rgb, opacity, cameras)[:, 0], torch.tensor([0.3, 0.3]))  # 0.2 + 0.1, 0.4 - 0.1


def test_fit_and_evaluation_use_each_cameras_gain(capture):
    """A capture whose colour.json gives one camera twice the gain: the fit's loss carries its training cameras'
    gains, and narf-eval renders that camera's views twice as bright and leaves the other cameras' views alone."""
    from fitting.config import load_config
    from fitting.run_folder import prepare_run_dir
    from pipelines.datasets.capture import ZjuCapture
    from pipelines.runs.fit import start_run
    from pipelines.runs.requests import EvalRequest
    from pipelines.runs.subject.evaluation import evaluate_run

    subject = capture / "synthetic" / "taichi"
    names = [c.name for c in ZjuCapture(subject).cameras]
    gains = np.ones((len(names), 3))

    def write(gains):
        record = {"method": "floor", "gains": gains, "points": [100] * 4, "residual": [0.0] * 4, "measured": [True] * 4}
        write_camera_colour(subject / "colour.json", names, record)

    write(gains)
    config = load_config("tiny", [f"data.subject={subject}", "data.ratio=1.0", "train.steps=2"])
    run = prepare_run_dir(capture / "run", False)
    trainer = start_run(run, torch.device("cpu"), config, progress=False)
    train_views = list(ZjuCapture(subject).protocol("narf").train_views)
    torch.testing.assert_close(trainer.colour_response.gains, torch.ones(len(train_views), 3))
    seen = []
    with mock.patch("fitting.trainer.batch_loss", side_effect=lambda *a, **k: seen.append(k) or batch_loss(*a, **k)):
        trainer.fit()
    assert seen and all(k["camera_colour"] is trainer.colour_response for k in seen)  # every training step
    request = EvalRequest(splits=("novel_pose",), progress=False, grids=0)
    before = evaluate_run(run, request)["splits"]["novel_pose"]["per_view"]
    brighter = 3
    gains[brighter] = 2.0
    write(gains)
    after = evaluate_run(run, request)["splits"]["novel_pose"]["per_view"]
    for a, b in zip(before, after):
        same = a["full"]["psnr"] == b["full"]["psnr"]
        assert same == (a["camera"] != brighter), (a["camera"], a["full"]["psnr"], b["full"]["psnr"])


class _FixedImages(torch.nn.Module):
    """A stand-in CNN that paints every output pixel (0.25, 0.25, 0.25) at opacity 1."""

    def forward(self, maps, bones, latent=None):
        n, size = maps.shape[0], maps.shape[-1]
        return torch.full((n, 3, size, size), 0.25), torch.ones(n, size, size)


def test_the_cnn_baselines_loss_takes_each_cameras_gain(capture):
    """The CNN baseline's colour term compares gain x output with each training image: with every gain 2 its MSE is
    that of a uniform 0.5 image, computed here from the stored targets."""
    from fitting.config import load_config
    from fitting.run_folder import prepare_run_dir
    from pipelines.runs.fit import start_run

    sets = ["model.name=cnn", "model.image_size=32", "train.images_per_step=4", "train.steps=1"]
    config = load_config("tiny", [f"data.data_root={capture}", "data.ratio=1.0", *sets])
    trainer = start_run(prepare_run_dir(capture / "run", False), torch.device("cpu"), config, progress=False)
    trainer.field = _FixedImages()
    chosen = torch.tensor([0, 1, 2])
    trainer.fit_data.camera_gains = torch.full((trainer.views.n_cameras, 3), 2.0)
    _, colour = trainer.image_loss(chosen)
    expected = (0.5 - trainer.rgb[chosen].float()).pow(2).mean()
    torch.testing.assert_close(colour, expected)


def test_the_command_writes_the_file_and_refuses_in_one_line(capture, capsys):
    """narf-camera-colour: without floor.json, or with a colour.json already there, one line and exit code 2. The
    synthetic capture's cameras record the same colours (narf-synth applies no gain), so every gain is 1 within 1 %
    (JPEG quality 95 moves single pixels by a level or two; the pair medians over the floor's points cancel that)."""
    from pipelines.cli.camera_colour import main
    from pipelines.cli.common import run_cli

    subject = capture / "synthetic" / "taichi"
    assert run_cli("narf-camera-colour", main, [str(subject), "--quiet"]) == 2
    assert capsys.readouterr().err.strip().endswith("no floor.json, so no floor to compare the cameras on")
    (subject / "floor.json").write_text(json.dumps({"up": [0, 0, -1], "height": 0.0, "source": "given"}))
    assert run_cli("narf-camera-colour", main, [str(subject), "--quiet", "--frames", "4"]) == 0
    record = json.loads((subject / "colour.json").read_text())
    gains = np.array([entry["gain"] for entry in record["cameras"].values()])
    assert all(entry["measured"] for entry in record["cameras"].values())
    np.testing.assert_allclose(gains, 1.0, atol=0.01)
    assert run_cli("narf-camera-colour", main, [str(subject), "--quiet"]) == 2
    assert "colour.json: exists (--overwrite replaces it)" in capsys.readouterr().err
    shutil.rmtree(subject / "mask")  # a capture with CIHP masks only, as some ZJU-MoCap subjects
    assert run_cli("narf-camera-colour", main, [str(subject), "--quiet", "--frames", "4", "--overwrite"]) == 0
