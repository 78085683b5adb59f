"""Opening a file never runs code from it: SMPL pickles, np.save(dict) files and checkpoints."""

import os
import pickle

import numpy as np
import pytest
import torch

from fitting.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from pipelines.datasets.errors import CaptureError
from pipelines.datasets.safe_pickle import UnsafePickleError, load_npy_object
from pipelines.datasets.smpl_files import SmplFileError, load_smpl_dict
from pipelines.datasets.zju_mocap import read_params


class _Payload:
    """Unpickling this calls os.system, which would create the marker file."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_smpl_pickle_with_a_payload_is_refused(tmp_path):
    marker = tmp_path / "ran"
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    path.write_bytes(pickle.dumps({"v_template": _Payload(marker)}, protocol=2))
    with pytest.raises(
        SmplFileError, match=r"SMPL_NEUTRAL.pkl: not a readable SMPL pickle \(refuses to load '(posix|os)\.system'"
    ):
        load_smpl_dict(path)
    assert not marker.exists()


def test_npy_dict_with_a_payload_is_refused_and_a_plain_one_loads(tmp_path):
    marker = tmp_path / "ran"
    np.save(tmp_path / "0.npy", np.array({"poses": _Payload(marker)}, dtype=object), allow_pickle=True)
    with pytest.raises(CaptureError, match=r"0.npy: unreadable \(refuses to load"):
        read_params(tmp_path / "0.npy")
    assert not marker.exists()
    good = {"poses": np.zeros((1, 72)), "Rh": np.ones((1, 3)), "Th": np.zeros((1, 3)), "shapes": np.zeros((1, 10))}
    np.save(tmp_path / "1.npy", good, allow_pickle=True)
    assert read_params(tmp_path / "1.npy").rh.tolist() == [1.0, 1.0, 1.0]
    np.save(tmp_path / "numeric.npy", np.arange(4.0))
    assert load_npy_object(tmp_path / "numeric.npy").tolist() == [0.0, 1.0, 2.0, 3.0]
    with pytest.raises(UnsafePickleError):
        np.save(tmp_path / "2.npy", np.array([_Payload(marker)], dtype=object), allow_pickle=True)
        load_npy_object(tmp_path / "2.npy")
    assert not marker.exists()


def test_checkpoint_with_a_payload_is_refused(tmp_path):
    marker = tmp_path / "ran"
    save_checkpoint(tmp_path, {"config": {}, "step": 1, "model": {"w": torch.zeros(2)}})
    assert load_checkpoint(tmp_path)["step"] == 1  # a real checkpoint: tensors and plain values
    torch.save({"format": 1, "config": {}, "step": 1, "model": _Payload(marker)}, tmp_path / "checkpoint.pt")
    with pytest.raises(CheckpointError, match="checkpoint.pt: corrupt or unreadable checkpoint") as refused:
        load_checkpoint(tmp_path)
    assert not marker.exists()
    # the message names the global it refused and never points the user at torch.load(weights_only=False)
    assert "GLOBAL" in str(refused.value) and "could run code" in str(refused.value)
    assert "weights_only" not in str(refused.value)


def test_npy_headers_are_parsed_one_thread_at_a_time(tmp_path, monkeypatch):
    """numpy parses a .npy header with ast.literal_eval, which CPython 3.11 cannot run in two threads at once: the
    readers hold one lock around it. A literal_eval that sleeps 2 ms counts the parses in flight; four threads each
    reading 10 dict files and 10 plain arrays (a fit's views) never overlap. Without the lock the 2-ms sleeps of
    four threads overlap on the first files."""
    import ast
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from pipelines.datasets.safe_pickle import load_npy

    for i in range(10):
        np.save(tmp_path / f"dict{i}.npy", {"poses": np.zeros((1, 72))}, allow_pickle=True)
        np.save(tmp_path / f"plain{i}.npy", np.zeros((6890, 3), np.float32))
    state = {"now": 0, "most": 0}
    guard, literal_eval = threading.Lock(), ast.literal_eval

    def counting(text):
        with guard:
            state["now"] += 1
            state["most"] = max(state["most"], state["now"])
        threading.Event().wait(0.002)
        try:
            return literal_eval(text)
        finally:
            with guard:
                state["now"] -= 1

    monkeypatch.setattr(ast, "literal_eval", counting)

    def read(_):
        for i in range(10):
            assert load_npy_object(tmp_path / f"dict{i}.npy").item()["poses"].shape == (1, 72)
            assert load_npy(tmp_path / f"plain{i}.npy").shape == (6890, 3)

    with ThreadPoolExecutor(4) as pool:
        list(pool.map(read, range(4)))
    assert state["most"] == 1
