"""Shading (narf.shading, docs/model.md §3): the spherical harmonics against scipy's and by quadrature, and NARF_D's
shaded colour: the albedo under a constant light, and turning the world with its light changes nothing."""

from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.special import sph_harm_y

from fitting.config import ConfigError, FitConfig, validate_config
from fitting.unseen import mirror_terms, sagittal_reflections
from narf.fields import build_field
from narf.fields.common import RadianceHead, cat_poses
from narf.shading import SH_C0, SH_C1, SH_C20, constant_lighting, irradiance, sh_basis
from tests.test_fields import _points, _random_pose

#: (degree l, order m) of each of sh_basis's 9 outputs
DEGREES_ORDERS = [(0, 0), (1, -1), (1, 0), (1, 1), (2, -2), (2, -1), (2, 0), (2, 1), (2, 2)]


def _sphere_grid(n_polar=8, n_azimuth=16):
    """Gauss-Legendre nodes in cos(polar) times equal azimuth steps: exact for polynomials of degree <= 2 n_polar - 1
    in z and trigonometric ones of degree < n_azimuth in the azimuth, so for products of two degree-2 harmonics."""
    cos_polar, weights = np.polynomial.legendre.leggauss(n_polar)
    azimuth = np.arange(n_azimuth) * 2 * np.pi / n_azimuth
    polar = np.arccos(cos_polar)
    polar_grid, azimuth_grid = np.meshgrid(polar, azimuth, indexing="ij")
    weight = np.repeat(weights[:, None], n_azimuth, axis=1) * 2 * np.pi / n_azimuth
    normals = np.stack(
        [np.sin(polar_grid) * np.cos(azimuth_grid), np.sin(polar_grid) * np.sin(azimuth_grid), np.cos(polar_grid)], -1
    )
    return polar_grid.ravel(), azimuth_grid.ravel(), normals.reshape(-1, 3), weight.ravel()


def test_basis_by_hand_at_the_pole():
    basis = sh_basis(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))[0]
    want = torch.tensor([SH_C0, 0, SH_C1, 0, 0, 0, 2 * SH_C20, 0, 0], dtype=torch.float64)
    assert torch.allclose(basis, want, atol=1e-15)  # float64, one product each


def test_basis_matches_scipy_real_harmonics_up_to_sign():
    """The real harmonics from scipy's complex ones: Y_l0, sqrt(2) Re Y_lm (m > 0), sqrt(2) Im Y_l|m| (m < 0); the
    sign of each is a convention (Condon-Shortley's (-1)^m), so the magnitudes are compared."""
    polar, azimuth, normals, _ = _sphere_grid()
    ours = sh_basis(torch.as_tensor(normals)).numpy()
    for k, (degree, order) in enumerate(DEGREES_ORDERS):
        complex_value = sph_harm_y(degree, abs(order), polar, azimuth)
        real = (
            complex_value.real if order == 0 else np.sqrt(2) * (complex_value.real if order > 0 else complex_value.imag)
        )
        # float64 trigonometry against polynomials of the same point: ~1e-15
        np.testing.assert_allclose(np.abs(ours[:, k]), np.abs(real), atol=1e-12)


def test_basis_is_orthonormal_over_the_sphere():
    _, _, normals, weight = _sphere_grid()
    basis = sh_basis(torch.as_tensor(normals)).numpy()
    gram = (basis * weight[:, None]).T @ basis
    np.testing.assert_allclose(gram, np.eye(9), atol=1e-12)  # an exact quadrature in float64 over 128 nodes


def test_constant_lighting_is_one_and_light_is_never_negative():
    normals = torch.nn.functional.normalize(torch.randn(100, 3, dtype=torch.float64), dim=-1)
    assert torch.allclose(irradiance(normals, constant_lighting().double()), torch.ones(100, 3, dtype=torch.float64))
    dark = constant_lighting().double()
    dark[:, 2] = 10.0  # a strong light from +z: its expansion is negative towards -z
    below = irradiance(torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64), dark)
    assert (below == 0).all()


def _shaded_field():
    torch.manual_seed(0)
    field = build_field("narf_d", width=16, encoding="grid", grid_levels=3, grid_max_resolution=16, shading=True)
    field.set_boxes(torch.zeros(19, 3), torch.full((19, 3), 0.6))
    torch.nn.init.normal_(field.grids.table, std=0.5)
    return field.double()


def test_under_a_constant_light_the_colour_is_the_albedo():
    """Lighting E = 1: the shaded model's colour is its albedo, the colour of the same model without shading."""
    shaded = _shaded_field()
    plain = build_field("narf_d", width=16, encoding="grid", grid_levels=3, grid_max_resolution=16).double()
    state = {k: v for k, v in shaded.state_dict().items() if "normal_out" not in k and "lighting" not in k}
    plain.load_state_dict(state)
    points, dirs = _points(4, 6, seed=3, dtype=torch.float64)
    pose = _random_pose(dtype=torch.float64).select(torch.zeros(4, dtype=torch.long))
    # float64, the same operations and one product by 1 (up to the coefficient's rounding, ~1e-16)
    assert torch.allclose(shaded(points, dirs, pose).rgb, plain(points, dirs, pose).rgb, atol=1e-12)


def test_turning_the_world_and_its_light_together_changes_no_colour():
    """Points, directions and part frames turned by Q, the pose features kept: every part-local input is the same,
    and the normals turn with Q. A first-degree light b . n (b = C1 (L_11, L_1-1, L_10)) turned with them (b -> Q b)
    gives every sample its colour back; the light left as it was does not."""
    field = _shaded_field()
    lighting = constant_lighting().double()
    lighting[:, 1:4] = torch.tensor([[0.9, -0.4, 0.3], [0.2, 0.8, -0.5], [-0.6, 0.1, 0.7]], dtype=torch.float64)
    field.head.lighting.data.copy_(lighting)
    points, dirs = _points(4, 6, seed=3, dtype=torch.float64)
    pose = _random_pose(dtype=torch.float64).select(torch.zeros(4, dtype=torch.long))
    before = field(points, dirs, pose).rgb
    q = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(7), dtype=torch.float64))[0]
    turned = torch.eye(4, dtype=torch.float64)
    turned[:3, :3] = q
    turned_pose = replace(pose, world_from_part=turned @ pose.world_from_part)  # the pose features kept
    with torch.no_grad():
        unturned_light = field(points @ q.T, dirs @ q.T, turned_pose).rgb
        xyz = lighting[:, [3, 1, 2]]  # (x, y, z) components of each channel's first degree
        field.head.lighting[:, [3, 1, 2]] = xyz @ q.T
        after = field(points @ q.T, dirs @ q.T, turned_pose).rgb
    # float64 through a 16-wide network: ~1e-14
    assert torch.allclose(after, before, atol=1e-10)
    assert (unturned_light - before).abs().max() > 1e-3


def test_shading_is_narf_d_only():
    config = FitConfig()
    config.model.name, config.model.shading = "narf_h", True
    with pytest.raises(ConfigError, match="model.shading: narf_h does not take it"):
        validate_config(config)
    assert SH_C0 == pytest.approx(0.28209479177387814)  # 1 / (2 sqrt(pi))


def test_a_pose_looks_its_normals_up_in_its_own_light_frame():
    """PoseBatch.light_from_world = L: the normal n is looked up at L n, the same as a first-degree light b . n turned
    by L^T (b -> L^T b); a mirror image takes its sagittal reflection (S = I - 2 n n^T, n the root's x axis)."""
    field = _shaded_field()
    lighting = constant_lighting().double()
    lighting[:, 1:4] = torch.tensor([[0.9, -0.4, 0.3], [0.2, 0.8, -0.5], [-0.6, 0.1, 0.7]], dtype=torch.float64)
    field.head.lighting.data.copy_(lighting)
    points, dirs = _points(4, 6, seed=3, dtype=torch.float64)
    frame_pose = _random_pose(dtype=torch.float64)
    reflection = sagittal_reflections(frame_pose)
    root_x = frame_pose.world_from_part[0, 0, :3, 0]
    # float64: one outer product
    assert torch.allclose(reflection[0], torch.eye(3, dtype=torch.float64) - 2 * torch.outer(root_x, root_x))
    assert torch.allclose(reflection[0] @ root_x, -root_x, atol=1e-12)
    lit = replace(frame_pose, light_from_world=reflection)
    ray_frames = torch.zeros(4, dtype=torch.long)
    with torch.no_grad():
        looked_up = field(points, dirs, lit.select(ray_frames)).rgb
        field.head.lighting[:, [3, 1, 2]] = lighting[:, [3, 1, 2]] @ reflection[0]  # b -> S^T b, as row vectors
        turned_light = field(points, dirs, frame_pose.select(ray_frames)).rgb
    assert torch.allclose(looked_up, turned_light, atol=1e-10)  # float64 through a 16-wide network
    both = cat_poses([frame_pose, lit])  # a batch without the frame counts as the identity
    assert torch.equal(both.light_from_world[0], torch.eye(3, dtype=torch.float64))
    assert torch.equal(both.light_from_world[1], reflection[0])


def test_the_mirror_term_lights_the_mirror_image_by_the_reflected_light():
    """mirror_terms: its first set keeps the frames' light (none: the identity), its second, the mirror images, carries
    each frame's sagittal reflection as light_from_world."""
    config = FitConfig()
    config.train.mirror_weight, config.train.mirror_rays = 0.1, 8
    poses, mirrored = _random_pose(n_frames=2, seed=1), _random_pose(n_frames=2, seed=2)
    (term,) = mirror_terms(config, poses, mirrored, torch.tensor([0, 1]), torch.Generator().manual_seed(0))
    seen, mirror = term.sets
    assert seen.poses.light_from_world is None
    assert torch.equal(mirror.poses.light_from_world, sagittal_reflections(poses))


def test_a_shading_head_refuses_a_missing_rotation_and_a_pose_a_misshapen_light_frame():
    head = RadianceHead({"x": 4}, {"d": 2}, width=8, shading=True)
    with pytest.raises(ValueError, match="rotation into the lighting"):
        head({"x": torch.randn(1, 2, 3, 4)}, {"d": torch.randn(1, 2, 3, 2)})
    pose = _random_pose(n_frames=2)
    with pytest.raises(ValueError, match="light_from_world"):
        replace(pose, light_from_world=torch.eye(3).expand(3, 3, 3))
