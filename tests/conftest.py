"""Shared fixtures: a session cache so the stand-in body model is generated once per test run."""

import os
import shutil
from pathlib import Path

import pytest

_CACHE = Path(__file__).resolve().parents[1] / ".cache" / "test"
os.environ.setdefault("NARF_CACHE", str(_CACHE))
os.environ.pop("NARF_SMPL_DIR", None)
if os.environ.get("PYTEST_XDIST_WORKER"):
    # `make test` runs one pytest-xdist worker per core; left alone, each worker's torch and OpenCV would start one
    # thread per core as well, and the n x n threads spin-wait against each other. One thread per worker, and for
    # the processes the tests start (OMP_NUM_THREADS is inherited), keeps every core busy without that.
    import cv2
    import torch

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    torch.set_num_threads(1)
    cv2.setNumThreads(1)


@pytest.fixture(autouse=True)
def _global_state_as_it_was():
    """Each test finds torch's and numpy's process-wide state as the session set it, whatever ran before it in the
    same worker: the thread count (a fit's sums run in another order with more threads, so its figures move; the
    benchmarks' harnesses set 2), the deterministic-algorithms switch and the default dtype a fit or a test sets,
    and the global random generators."""
    import random

    import numpy as np
    import torch

    threads, dtype = torch.get_num_threads(), torch.get_default_dtype()
    deterministic = torch.are_deterministic_algorithms_enabled()
    warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
    states = torch.random.get_rng_state(), np.random.get_state(), random.getstate()
    yield
    torch.set_num_threads(threads)
    torch.set_default_dtype(dtype)
    torch.use_deterministic_algorithms(deterministic, warn_only=warn_only)
    torch.random.set_rng_state(states[0])
    np.random.set_state(states[1])
    random.setstate(states[2])


@pytest.fixture(scope="session")
def body_model():
    from pipelines.body.model import BodyModel

    return BodyModel()


@pytest.fixture(scope="session")
def body_model64():
    import torch

    from pipelines.body.model import BodyModel

    return BodyModel(dtype=torch.float64)


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory):
    """A small synthetic capture: 4 frames x 4 cameras at 256^2, 3 calibration shots, 2 close-ups per camera."""
    from pipelines.synthetic.capture import SynthConfig, generate_capture

    out = tmp_path_factory.mktemp("capture") / "taichi"
    return generate_capture(
        out,
        SynthConfig(resolution=256, frames=4, cameras=4, calib_shots=3, calib_close_ups=2, workers=1),
        progress=False,
    )


@pytest.fixture(scope="session")
def tiny_capture_313(tmp_path_factory):
    from pipelines.synthetic.capture import SynthConfig, generate_capture

    out = tmp_path_factory.mktemp("capture313") / "CoreView_313"
    return generate_capture(
        out, SynthConfig(resolution=64, frames=3, cameras=2, calib_shots=0, layout="313", workers=1), progress=False
    )


@pytest.fixture(scope="session")
def data_root_64(tmp_path_factory):
    """A data root whose synthetic taichi capture is 10 frames x 4 cameras at 64^2."""
    from pipelines.synthetic.capture import SynthConfig, generate_capture

    root = tmp_path_factory.mktemp("data64")
    generate_capture(
        root / "synthetic" / "taichi",
        SynthConfig(resolution=64, frames=10, cameras=4, calib_shots=0, workers=1),
        progress=False,
    )
    return root


@pytest.fixture(scope="session")
def tiny_run(data_root_64, tmp_path_factory):
    """A 2-step tiny NARF_D fit of the 64^2 capture (weights barely trained: for plumbing, not quality)."""
    import torch

    from fitting.config import load_config
    from fitting.run_folder import prepare_run_dir
    from pipelines.runs.fit import start_run

    config = load_config("tiny", [f"data.data_root={data_root_64}", "data.ratio=1.0", "train.steps=2"])
    run = prepare_run_dir(tmp_path_factory.mktemp("tiny_run") / "run", False)
    start_run(run, torch.device("cpu"), config, progress=False).fit()
    return run


@pytest.fixture()
def capture(data_root_64, tmp_path):
    """A private copy of the 64^2 synthetic capture under a data root of its own (to damage in a test)."""
    root = tmp_path / "data"
    shutil.copytree(data_root_64 / "synthetic" / "taichi", root / "synthetic" / "taichi")
    return root


#: the keypoint noise of the synthetic recording (pixels)
NOISE_PX = 1.0


@pytest.fixture(scope="session")
def recording(tmp_path_factory):
    """The synthetic capture (10 frames x 4 cameras, 256^2) written back as a raw recording: videos, a Qualisys file
    of the true cameras, OpenPose JSON of the true joints with ``NOISE_PX`` of noise, the true masks."""
    from pipelines.synthetic.capture import SynthConfig, generate_capture
    from pipelines.synthetic.recording import write_recording

    root = tmp_path_factory.mktemp("recording")
    config = SynthConfig(resolution=256, frames=10, cameras=4, calib_shots=0, calib_close_ups=0, workers=1)
    generate_capture(root / "truth", config, progress=False)
    write_recording(root / "truth", root / "rec", noise_px=NOISE_PX)
    return root
