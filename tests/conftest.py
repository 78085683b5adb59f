"""Shared fixtures: a session cache so the stand-in body model is generated once per test run."""

import os
from pathlib import Path

import pytest

_CACHE = Path(__file__).resolve().parents[1] / ".cache" / "test"
os.environ.setdefault("NARF_CACHE", str(_CACHE))
os.environ.pop("NARF_SMPL_DIR", None)


@pytest.fixture(scope="session")
def body_model():
    from pipelines.body_model import BodyModel

    return BodyModel()


@pytest.fixture(scope="session")
def body_model64():
    import torch

    from pipelines.body_model import BodyModel

    return BodyModel(dtype=torch.float64)
