"""Typed configs: Literal choices, the model-options table, settings of another kind refused, and run folders
written by older versions (``data.dataset``, ``train.world_size``, the checkpoint's ``kind``) still loading."""

import typing

import pytest
import torch

from fitting.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from fitting.config import CONFIG_DIR, ConfigError, FitConfig, ModelName, RunKindName, load_config
from fitting.fitted import load_fitted
from fitting.model_setup import make_field
from narf.fields import MODEL_SPECS
from pipelines.runs.kinds import RUN_KINDS


def test_names_agree_across_the_tables():
    assert set(typing.get_args(ModelName)) == set(MODEL_SPECS)
    assert set(typing.get_args(RunKindName)) == set(RUN_KINDS)
    for kind in RUN_KINDS.values():  # every default preset exists and is of its kind
        for preset in (*kind.presets, *(kind.image_presets or ())):
            assert load_config(preset).kind == kind.name


def test_the_commands_offer_every_kind_split_and_video():
    """narf-fit, narf-eval and narf-render-video list the choices without importing the kinds (fast --help)."""
    from pipelines.cli import eval as cli_eval
    from pipelines.cli import fit as cli_fit
    from pipelines.cli import render_video

    assert set(cli_fit.KIND_NAMES) == set(RUN_KINDS)
    assert set(cli_eval.SPLITS) == {s for k in RUN_KINDS.values() for s in k.splits} | {"all"}
    assert set(render_video.VIDEO_KINDS) == {v for k in RUN_KINDS.values() for v in k.videos}


def test_every_preset_loads_and_builds_its_model():
    for path in sorted(CONFIG_DIR.glob("*.yaml")):
        config = load_config(path.stem)
        assert sum(p.numel() for p in make_field(config).parameters()) > 0, path.name


@pytest.mark.parametrize(
    "override, message",
    [
        ("data.protocol=nb", "expected one of narf, neuralbody, got 'nb'"),
        ("model.name=narf", "expected one of narf_d,"),
        ("kind=zju", "expected one of subject, autoencoder, rigid"),
        ("train.precision=fp16", "expected one of fp32, bf16"),
        ("model.temperature=5", "model.temperature: narf_d does not take it (only narf_p)"),
        ("train.encoder_lr=0.01", "train.encoder_lr: only autoencoder runs use it (this is a subject run)"),
        ("data.ratio=0", "config key 'data.ratio': must be in (0, 1], got 0.0"),
        ("model.view_freqs=5", "config key 'model.view_freqs': must be in .0, 4., got 5"),
        ("model.pose_dropout=1", "config key 'model.pose_dropout': must be in .0, 1), got 1.0"),
        (
            "render.val_fine=4",
            "render.val_fine: set render.val_coarse too (val_coarse 0 takes both of the evaluation's)",
        ),
        ("render.val_coarse=1", "config key 'render.val_coarse': must be 0 (the evaluation's) or >= 2, got 1"),
        ("model.encoding=hash", "expected one of frequency, grid, got 'hash'"),
        ("model.grid_levels=0", "config key 'model.grid_levels': must be in .1, 32., got 0"),
        ("model.grid_log2_rows=30", "config key 'model.grid_log2_rows': must be in .4, 24., got 30"),
        ("model.grid_max_resolution=4", "model.grid_max_resolution: must be >= model.grid_min_resolution (8), got 4"),
        ("train.grid_lr=0", "config key 'train.grid_lr': must be > 0, got 0.0"),
        ("train.grid_smoothness=-1", "config key 'train.grid_smoothness': must be >= 0 (0: off), got -1.0"),
        ("train.grid_smooth_points=0", "config key 'train.grid_smooth_points': must be >= 1, got 0"),
    ],
)
def test_bad_values_name_their_key(override, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_config("tiny", [override])


def test_model_options_reach_the_constructor():
    assert make_field(load_config("tiny", ["model.name=narf_p", "model.temperature=0.5"])).temperature == 0.5
    assert make_field(load_config("tiny", ["model.name=p_nerf", "model.pose_in_color=false"])).pose_in_color is False


def test_colour_conditioning_and_the_window_reach_the_field(tmp_path):
    """The model config's colour options and the coarse-to-fine window (alpha from 4 to 10 over 1,000 steps: 7 at
    step 500, open at 1,000) reach the field, in training and in a run loaded for evaluation at its step."""
    sets = ["model.view_freqs=1", "model.view_jitter=30", "model.pose_dropout=0.25", "train.window_steps=1000"]
    config = load_config("tiny", sets)
    field = make_field(config, 500)
    assert (field.view_freqs, field.pose_dropout, field.point_window) == (1, 0.25, 7.0)
    assert field.view_jitter == pytest.approx(torch.pi / 6, rel=1e-12)  # degrees to radians, float64
    assert make_field(config).point_window == 4.0 and make_field(config, 1000).point_window is None
    save_checkpoint(tmp_path, {"config": config.to_dict(), "step": 250, "model": field.state_dict()})
    assert load_fitted(tmp_path).field.point_window == 5.5
    with pytest.raises(ConfigError, match="model.pose_dropout: p_nerf's density reads the pose features"):
        load_config("tiny", ["model.name=p_nerf", "model.pose_dropout=0.5"])
    assert make_field(load_config("tiny", ["model.pose_freqs=1"])).pose_freqs == 1
    with pytest.raises(ConfigError, match="model.pose_freqs: p_nerf's density reads the pose features"):
        load_config("tiny", ["model.name=p_nerf", "model.pose_freqs=0"])


@pytest.mark.parametrize("legacy, kind", [("zju", "subject"), ("thuman", "autoencoder"), ("rigid", "rigid")])
def test_old_run_folders_load(tmp_path, legacy, kind):
    """A checkpoint as older versions wrote it: the kind in data.dataset, the process count in train.world_size,
    and (autoencoders) ``kind: autoencoder`` beside the weights."""
    preset = {"subject": "tiny", "autoencoder": "ae_tiny", "rigid": "rigid_tiny"}[kind]
    config = load_config(preset)
    saved = config.to_dict()
    del saved["kind"]
    saved["data"]["dataset"] = legacy
    saved["train"]["world_size"] = 1
    extra = {"kind": "autoencoder"} if kind == "autoencoder" else {}
    save_checkpoint(tmp_path, {"config": saved, "step": 3, "model": make_field(config).state_dict(), **extra})
    fitted = load_fitted(tmp_path, kind=kind)
    assert fitted.config == config and fitted.step == 3


def test_foreign_configs_and_weights_fail_with_the_file(tmp_path):
    config = load_config("tiny")
    saved = config.to_dict()
    del saved["kind"]
    saved["data"]["dataset"] = "h36m"
    (tmp_path / "a").mkdir()
    save_checkpoint(tmp_path / "a", {"config": saved, "step": 0, "model": {}})
    with pytest.raises(CheckpointError, match="a: saved config: unknown data.dataset 'h36m'"):
        load_fitted(tmp_path / "a")
    (tmp_path / "b").mkdir()
    wrong = make_field(load_config("tiny", ["model.name=narf_h"])).state_dict()
    save_checkpoint(tmp_path / "b", {"config": config.to_dict(), "step": 0, "model": wrong})
    with pytest.raises(CheckpointError, match="its weights do not fit the narf_d model of its config"):
        load_fitted(tmp_path / "b")
    with pytest.raises(CheckpointError, match="holds a subject run; this needs a rigid run"):
        load_fitted(tmp_path / "b", kind="rigid")
    assert isinstance(load_checkpoint(tmp_path / "b")["model"], dict)


def test_run_state_is_not_a_setting():
    assert "world_size" not in FitConfig().to_dict()["train"]
    with pytest.raises(ConfigError, match="unknown config key 'train.world_size'"):
        load_config("tiny", ["train.world_size=2"])
    assert torch.get_default_dtype() == torch.float32


@pytest.mark.parametrize(
    "override, message",
    [
        ("train.lr=[", "override 'train.lr=[': the value is not plain YAML"),
        ("train.lr=!!python/object/apply:os.system [true]", "the value is not plain YAML"),
        ("train.steps=.inf", "config key 'train.steps': expected a finite number, got inf"),
        ("train.steps=.nan", "config key 'train.steps': expected a finite number, got nan"),
        ("train.lr=.inf", "config key 'train.lr': expected a finite number, got inf"),
        ("train.log_every=0", "config key 'train.log_every': must be >= 1, got 0"),
        ("render.chunk=0", "config key 'render.chunk': must be >= 1, got 0"),
        ("data.frame_stride=0", "config key 'data.frame_stride': must be >= 1, got 0"),
        ("train.checkpoint_minutes=-1", "config key 'train.checkpoint_minutes': must be >= 0 (0: after every step)"),
        ("train.lr_decay=1.5", "config key 'train.lr_decay': must be in (0, 1]"),
        ("train.colour_delta=-0.1", "config key 'train.colour_delta': must be >= 0 (0: the squared error)"),
        ("train.mirror_weight=-1", "config key 'train.mirror_weight': must be >= 0 (0: off)"),
        ("train.body_fraction=0.9", "the shares of body and border rays exceed 1"),
        ("train.steps=2.5", "config key 'train.steps': expected an integer, got 2.5"),
    ],
)
def test_bad_settings_end_in_one_line_before_anything_is_written(override, message, tmp_path, capsys):
    from pipelines.cli import fit as cli_fit
    from pipelines.cli.common import run_cli

    out = tmp_path / "run"
    assert run_cli("narf-fit", cli_fit.main, ["--config", "tiny", "--out", str(out), "--set", override]) == 2
    err = capsys.readouterr().err
    assert err.startswith("narf-fit: error: ") and message in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


@pytest.mark.parametrize("text", ["1e-3", "1E-3", "0.001", ".001", "+1e-3"])
def test_numbers_as_users_type_them(text, tmp_path):
    """YAML 1.1 reads 1e-3 (no dot) as a string, in --set and in preset files alike; both mean 0.001."""
    assert load_config("tiny", [f"train.lr={text}"]).train.lr == 0.001
    preset = tmp_path / "mine.yaml"
    preset.write_text(f"train:\n  lr: {text}\n  steps: 1e3\n")
    config = load_config(str(preset))
    assert config.train.lr == 0.001 and config.train.steps == 1000 and isinstance(config.train.steps, int)


def test_a_presets_model_section_applies_to_its_model_before_the_overrides(tmp_path):
    """The autoencoder presets train P-NeRF and NARF_H at lr 0.001 (supplement §F); other models keep the preset's
    rate, an override still wins, and a section naming no model is refused."""
    for preset in ("ae_cpu", "ae_paper", "ae_tiny"):
        assert load_config(preset, ["model.name=p_nerf"]).train.lr == 0.001
        assert load_config(preset, ["model.name=narf_h"]).train.lr == 0.001
        assert load_config(preset).train.lr == 0.01
        assert load_config(preset, ["model.name=narf_h", "train.lr=0.05"]).train.lr == 0.05
    bad = tmp_path / "bad.yaml"
    bad.write_text("models:\n  narf_x:\n    train:\n      lr: 0.1\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: models: unknown model\(s\) \['narf_x'\]"):
        load_config(str(bad))


def test_the_sparse_paper_preset_is_the_paper_preset_with_the_cpu_presets_levers():
    """paper_sparse differs from paper in the four settings that docs/results measured on the GPU, and each holds the
    CPU preset's value (docs/guides/fitting.md, *Few cameras*)."""
    import dataclasses

    def flat(config):
        return {
            f"{s}.{k}": v
            for s, part in dataclasses.asdict(config).items()
            if isinstance(part, dict)
            for k, v in part.items()
        }

    paper, sparse, cpu = (flat(load_config(name)) for name in ("paper", "paper_sparse", "cpu"))
    changed = {key for key in paper if paper[key] != sparse[key]}
    assert changed == {"model.view_freqs", "model.body_shell", "model.surface_shell", "train.lr_anneal"}
    assert all(sparse[key] == cpu[key] for key in changed)
