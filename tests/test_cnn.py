import pytest
import torch

from narf.bone_maps import N_CHANNELS, bone_maps, bone_pose_vector
from narf.fields.cnn import POSE_DIM, CnnBaseline, ConditionalBatchNorm
from narf.kinematics import SMPL_PARENTS


def _skeleton_in_front_of_camera():
    """Joints on a vertical line at x = 0, z = 2 m: joint j at y = -0.5 + j / 23."""
    cam_from_joint = torch.eye(4).repeat(24, 1, 1)
    for j in range(24):
        cam_from_joint[j, :3, 3] = torch.tensor([0.0, -0.5 + j / 23, 2.0])
    return cam_from_joint


def test_bone_maps_hand_computed():
    K = torch.tensor([[64.0, 0, 32], [0, 64.0, 32], [0, 0, 1]])
    maps = bone_maps(_skeleton_in_front_of_camera(), K, 64)
    assert maps.shape == (N_CHANNELS, 64, 64)
    # joint 0 projects to (32, 32 - 16) = (32, 16): its square covers rows 14..18 at column 32
    assert maps[20, 16, 32] == 1 and maps[20, 16, 35] == 0 and maps[20, 14:19, 30:35].sum() == 25
    # bones lie on column 32 (thickness 1.5 px), disparity 1 / 2 m
    bone_rows = maps[0, :, 32] > 0
    assert bone_rows.any() and torch.allclose(maps[0, bone_rows, 32], torch.tensor(0.5))  # 1/2: exact in float32
    assert maps[0, :, 40].max() == 0
    ramp = torch.linspace(-1, 1, 64)
    # the same linspace computed twice in float32: allclose's defaults (rtol 1e-5) cover any summation order
    assert torch.allclose(maps[44, 0], ramp) and torch.allclose(maps[45, :, 0], ramp)
    # part 0 (pelvis) owns the bones pelvis -> hips and spine1
    assert maps[1].sum() > 0 and all(SMPL_PARENTS[c] == 0 for c in (1, 2, 3))


def test_cnn_baseline_size_and_outputs():
    from narf.fields import build_model

    model = build_model("cnn")
    assert isinstance(model, CnnBaseline) and isinstance(build_model("narf_d", width=8), torch.nn.Module)
    params = sum(p.numel() for p in model.parameters())
    assert params == pytest.approx(15.6e6, rel=0.05)  # 15.87M: the supplement gives no layer table, only "15.6M"
    maps = torch.stack(
        [bone_maps(_skeleton_in_front_of_camera(), torch.tensor([[128.0, 0, 64], [0, 128, 64], [0, 0, 1]]), 128)] * 2
    )
    pose = bone_pose_vector(_skeleton_in_front_of_camera())[None].expand(2, -1)
    assert pose.shape == (2, POSE_DIM)
    rgb, mask = model(maps, pose)
    assert rgb.shape == (2, 3, 128, 128) and mask.shape == (2, 128, 128)
    assert ((rgb >= 0) & (rgb <= 1)).all() and mask.max() < 0.1  # sigmoid(logit - 5) starts near 0
    (rgb.mean() + mask.mean()).backward()
    assert model.stem.weight.grad is not None
    with pytest.raises(ValueError, match="maps"):
        model(torch.zeros(1, 45, 128, 128), pose[:1])


def test_cnn_autoencoder_conditions_every_norm_on_the_code():
    torch.manual_seed(0)
    model = CnnBaseline(image_size=32, latent_dim=4)
    plain = CnnBaseline(image_size=32)
    # each conditional norm's affine map takes the 2 L code beside the 228 pose values: 2 C x 8 more weights
    extra = sum(2 * m.norm.num_features * 8 for m in model.modules() if isinstance(m, ConditionalBatchNorm))
    assert sum(p.numel() for p in model.parameters()) - sum(p.numel() for p in plain.parameters()) == extra
    maps = torch.rand(2, N_CHANNELS, 32, 32)
    pose = torch.randn(2, POSE_DIM)
    with pytest.raises(ValueError, match="needs a code"):
        model(maps, pose)
    with pytest.raises(ValueError, match="latent"):
        model(maps, pose, torch.zeros(2, 4))
    codes = torch.randn(2, 8)
    model.eval()
    with torch.no_grad():  # zero-initialised affine maps: the code has no effect until trained
        assert torch.equal(model(maps, pose, codes)[0], model(maps, pose, torch.zeros(2, 8))[0])
        for m in model.modules():
            if isinstance(m, ConditionalBatchNorm):
                m.affine.weight.normal_(0, 0.05)
        # gamma, beta now move by ~0.05 |z| ~ 0.1 per channel: far above float32 noise in the outputs
        assert (model(maps, pose, codes)[0] - model(maps, pose, torch.zeros(2, 8))[0]).abs().max() > 1e-3
    with pytest.raises(ValueError, match="multiple of 32"):
        CnnBaseline(image_size=48)
