import os
import pickle

import numpy as np
import pytest
import scipy.sparse
import smplx
import torch
import trimesh

from pipelines.body.locate import resolve_smpl_file
from pipelines.body.standin import REST_JOINTS
from pipelines.datasets.smpl_files import SmplFileError, convert_official_pickle, load_smpl_dict


@pytest.fixture(scope="module")
def standin(body_model):
    return load_smpl_dict(body_model.path)


def test_standin_has_smpl_layout(standin):
    assert standin["v_template"].shape == (6890, 3)
    assert standin["f"].shape == (13776, 3) and standin["f"].dtype == np.uint32
    assert standin["shapedirs"].shape == (6890, 3, 10) and standin["posedirs"].shape == (6890, 3, 207)
    assert scipy.sparse.isspmatrix_csc(standin["J_regressor"]) and standin["J_regressor"].shape == (24, 6890)
    # float64 sums of <= a few hundred weights: ~1e-14, inside allclose's default rtol 1e-5
    assert np.allclose(np.asarray(standin["J_regressor"].sum(axis=1)).ravel(), 1.0)
    assert np.allclose(standin["weights"].sum(axis=1), 1.0) and (standin["weights"] >= 0).all()
    assert standin["kintree_table"][0, 0] == 4294967295
    # the rings at the joints regress them exactly: float64 weighted means of points ~1 m, ~1e-15
    assert np.abs(standin["J_regressor"] @ standin["v_template"] - REST_JOINTS).max() < 1e-9


def test_standin_is_one_closed_surface(standin):
    mesh = trimesh.Trimesh(standin["v_template"], standin["f"], process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.euler_number == 2
    assert 0.05 < mesh.volume < 0.12  # m^3: a 50-120 kg adult
    height = mesh.bounds[1, 1] - mesh.bounds[0, 1]
    assert 1.6 < height < 1.9


def test_real_smplx_loads_the_file_and_extra_joints_are_on_the_body(body_model, standin):
    model = smplx.create(str(body_model.path.parents[1]), model_type="smpl", gender="neutral")
    out = model()
    assert out.vertices.shape == (1, 6890, 3) and out.joints.shape == (1, 45, 3)
    joints = out.joints[0].detach().numpy()
    nose, left_hand_tip, left_heel = joints[24], joints[36], joints[31]  # nose, lindex tip, LHeel
    assert joints[15, 1] < nose[1] < joints[15, 1] + 0.12 and nose[2] > 0.1
    assert left_hand_tip[0] > 0.8 and left_heel[1] < -1.1 and left_heel[2] < -0.05


def test_shape_components_change_height_and_girth(body_model):
    rest = body_model.rest_body(torch.zeros(1, 10)).vertices[0]
    for component, axis in ((0, 1), (2, 1)):
        betas = torch.zeros(1, 10)
        betas[0, component] = 2.0
        taller = body_model.rest_body(betas).vertices[0]
        assert (taller[:, axis].max() - taller[:, axis].min()) > (rest[:, axis].max() - rest[:, axis].min()) + 0.05
    betas = torch.zeros(1, 10)
    betas[0, 1] = 2.0
    heavy = trimesh.Trimesh(body_model.rest_body(betas).vertices[0].numpy(), body_model.faces, process=False)
    assert heavy.volume > 1.2 * trimesh.Trimesh(rest.numpy(), body_model.faces, process=False).volume


def test_elbow_bend_keeps_surface_smooth(body_model):
    poses = torch.zeros(1, 72)
    poses[0, 18 * 3 + 1] = 1.5  # left elbow
    posed = body_model.pose_zju(poses, torch.zeros(1, 3), torch.zeros(1, 3), torch.zeros(1, 10)).vertices[0]
    rest = body_model.rest_body(torch.zeros(1, 10)).vertices[0]
    edges = trimesh.Trimesh(rest.numpy(), body_model.faces, process=False).edges_unique
    edges = torch.as_tensor(np.array(edges))
    length = lambda v: (v[edges[:, 0]] - v[edges[:, 1]]).norm(dim=1)  # noqa: E731
    stretch = length(posed) / length(rest)
    assert stretch.max() < 3.0  # no tearing: no edge more than triples in length


def _fake_official_pickle(standin, path):
    """Imitate the official files: chumpy 'Ch' objects wrapping arrays, pickled by Python 2 (latin1)."""

    class Ch:  # pickled as chumpy.ch.Ch
        pass

    Ch.__module__, Ch.__qualname__, Ch.__name__ = "chumpy.ch", "Ch", "Ch"
    import sys
    import types

    fake = types.ModuleType("chumpy.ch")
    fake.Ch = Ch
    sys.modules["chumpy"], sys.modules["chumpy.ch"] = types.ModuleType("chumpy"), fake
    try:
        wrapped = {}
        for key, value in standin.items():
            if key in ("v_template", "shapedirs", "posedirs", "weights", "J"):
                obj = Ch()
                obj.__dict__.update({"x": np.asarray(value), "_dirty_vars": set()})
                wrapped[key] = obj
            else:
                wrapped[key] = value
        with open(path, "wb") as handle:
            pickle.dump(wrapped, handle, protocol=2)
    finally:
        del sys.modules["chumpy"], sys.modules["chumpy.ch"]


def test_chumpy_free_converter(standin, tmp_path):
    src, dst = tmp_path / "basicModel_neutral_lbs_10_207_0_v1.0.0.pkl", tmp_path / "out" / "SMPL_NEUTRAL.pkl"
    _fake_official_pickle(standin, src)
    with pytest.raises(ModuleNotFoundError):
        with open(src, "rb") as handle:
            pickle.load(handle, encoding="latin1")  # what smplx would do
    convert_official_pickle(src, dst)
    model = smplx.SMPL(str(dst))
    # smplx stores v_template as float32: half an ulp at 1 m is 6e-8; 1e-6 m covers values up to ~16 m
    assert np.allclose(model.v_template.numpy(), standin["v_template"], atol=1e-6)
    assert resolve_smpl_file(tmp_path) == src
    assert resolve_smpl_file(tmp_path / "out") == dst


def test_bad_smpl_files_give_clear_errors(tmp_path, standin):
    with pytest.raises(SmplFileError, match="no such SMPL model file"):
        load_smpl_dict(tmp_path / "nope.pkl")
    (tmp_path / "junk.pkl").write_bytes(b"not a pickle")
    with pytest.raises(SmplFileError, match="junk.pkl: not a readable SMPL pickle"):
        load_smpl_dict(tmp_path / "junk.pkl")
    broken = dict(standin, weights=standin["weights"][:, :20])
    with open(tmp_path / "broken.pkl", "wb") as handle:
        pickle.dump(broken, handle)
    with pytest.raises(SmplFileError, match=r"'weights' has shape \(6890, 20\)"):
        load_smpl_dict(tmp_path / "broken.pkl")
    with pytest.raises(SmplFileError, match="no SMPL model file"):
        resolve_smpl_file(
            tmp_path / "empty_dir_that_exists" if (tmp_path / "empty_dir_that_exists").mkdir() is None else None
        )


def test_a_commands_smpl_choice_ends_with_it(standin, tmp_path, monkeypatch):
    """``--smpl-dir`` is the default model of the command's own calls only: a CLI main run through ``run_cli``
    resolves it, and neither the environment nor a later call in the same process sees it; ``chosen_smpl_dir``
    scopes a library call the same way, and ``$NARF_SMPL_DIR`` is still read as the default."""
    from pipelines.body.locate import chosen_smpl_dir, default_smpl_dir
    from pipelines.cli.common import run_cli, use_smpl_dir

    monkeypatch.delenv("NARF_SMPL_DIR", raising=False)
    other = tmp_path / "other" / "SMPL_NEUTRAL.pkl"
    other.parent.mkdir()
    other.write_bytes(b"")  # resolving only looks at the name
    seen = []

    def main(argv):
        use_smpl_dir(str(other.parent))
        seen.append(resolve_smpl_file())

    assert run_cli("narf-test", main, []) == 0
    assert seen == [other]
    assert default_smpl_dir() is None and "NARF_SMPL_DIR" not in os.environ
    with chosen_smpl_dir(other.parent):
        assert resolve_smpl_file() == other
    assert resolve_smpl_file() != other
    monkeypatch.setenv("NARF_SMPL_DIR", str(other))
    assert resolve_smpl_file() == other


@pytest.mark.parametrize("command", ["eval", "render_video", "export_mesh", "view"])
def test_a_commands_main_called_directly_keeps_its_smpl_choice(command, tmp_path, monkeypatch):
    """A command's ``main`` called directly (not through ``run_cli``) leaves no ``--smpl-dir`` choice behind, however
    it ends (here: the run folder is missing, after the choice was made). (Checked against the mains without their
    own context: the choice leaked into the caller.)"""
    import importlib

    from pipelines.body.locate import default_smpl_dir

    monkeypatch.delenv("NARF_SMPL_DIR", raising=False)
    main = importlib.import_module(f"pipelines.cli.{command}").main
    chosen = []
    monkeypatch.setattr("pipelines.runs.kinds.open_run", lambda run: chosen.append(default_smpl_dir()) or 1 / 0)
    argv = {"eval": ["--split", "novel_view"], "render_video": [], "export_mesh": ["--frame", "0", "--out", "x.ply"]}
    with pytest.raises(ZeroDivisionError):  # the stand-in for open_run, after the choice was made
        main(["--run", str(tmp_path), "--smpl-dir", str(tmp_path), *argv.get(command, [])])
    assert chosen == [str(tmp_path)] and default_smpl_dir() is None
