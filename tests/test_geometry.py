import math

import pytest
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix as so3_exp
from kornia.geometry.liegroup import Se3
from kornia.geometry.linalg import inverse_transformation as invert_rigid
from kornia.geometry.linalg import transform_points

from narf.geometry import check_shape, se3_exp, se3_log, so3_log


def _random_rotvecs(n, angles, gen):
    axis = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    return axis * angles[:, None]


@pytest.fixture
def gen():
    return torch.Generator().manual_seed(0)


ANGLES = torch.tensor(
    [0.0, 1e-9, 1e-5, 5e-4, 1e-3, 0.3, 1.0, 2.0, 3.0, math.pi - 1e-3, math.pi - 1e-6, math.pi], dtype=torch.float64
)


class TestSe3Log:
    def test_roundtrip_random_including_near_zero_and_pi(self, gen):
        angles = ANGLES.repeat(20)
        omega = _random_rotvecs(len(angles), angles, gen)
        u = torch.randn(len(angles), 3, generator=gen, dtype=torch.float64)
        xi = torch.cat([omega, u], -1)
        transform = se3_exp(xi)
        back = se3_log(transform)
        # At exactly pi the axis sign is ambiguous: compare the transforms instead. float64: near theta = 0 the
        # Taylor switch at 1e-3 leaves a truncation error ~theta^4/120 ~ 1e-14, and near pi the axis comes from
        # (R + R^T)/2 whose conditioning is 1/(1 - cos) ~ 1, so errors stay ~1e-12, under 1e-9 / 1e-8
        assert torch.allclose(se3_exp(back), transform, atol=1e-9)
        regular = angles < math.pi - 1e-3
        assert torch.allclose(back[regular], xi[regular], atol=1e-8)

    def test_matches_kornia_reference(self, gen):
        angles = torch.rand(200, generator=gen, dtype=torch.float64) * 3.0
        transform = se3_exp(
            torch.cat([_random_rotvecs(200, angles, gen), torch.randn(200, 3, generator=gen, dtype=torch.float64)], -1)
        )
        ref = Se3.from_matrix(transform).log()  # kornia: (translation part, rotation part)
        ours = se3_log(transform)
        # kornia goes through quaternions, we through arccos: both float64, angles <= 3 rad (away from pi, where
        # arccos loses digits as sqrt(eps) ~ 1e-8 only at the very end)
        assert torch.allclose(ours[:, :3], ref[:, 3:], atol=1e-8)
        assert torch.allclose(ours[:, 3:], ref[:, :3], atol=1e-8)

    def test_so3_exp_is_rodrigues(self, gen):
        from smplx.lbs import batch_rodrigues

        omega = _random_rotvecs(50, torch.rand(50, generator=gen, dtype=torch.float64) * 3, gen)
        # two float64 implementations of Rodrigues' formula (~10 operations on entries <= 1: ~1e-15); the log of
        # angles up to 3 rad loses up to ~1e-12 in arccos near its end points
        assert torch.allclose(so3_exp(omega), batch_rodrigues(omega), atol=1e-10)
        assert torch.allclose(so3_log(so3_exp(omega)), omega, atol=1e-9)

    def test_gradcheck(self, gen):
        xi = torch.cat(
            [
                _random_rotvecs(4, torch.tensor([0.2, 1.0, 2.0, 2.5], dtype=torch.float64), gen),
                torch.randn(4, 3, generator=gen, dtype=torch.float64),
            ],
            -1,
        ).requires_grad_()
        assert torch.autograd.gradcheck(lambda x: se3_log(se3_exp(x)), (xi,))

    def test_a_plain_twist_gives_a_plain_matrix(self, gen):
        """kornia holds the rotation as an nn.Parameter; a twist without gradient must not give a matrix that carries a
        graph (a pose built from it would then need a gradient in every model that reads it)."""
        xi = torch.randn(3, 6, generator=gen, dtype=torch.float64)
        assert not se3_exp(xi).requires_grad
        assert se3_exp(xi.clone().requires_grad_()).requires_grad

    def test_bad_shape_names_argument(self):
        with pytest.raises(ValueError, match=r"transform: expected shape \(\.\.\., 4, 4\), got \(3, 3\)"):
            se3_log(torch.eye(3))


def test_invert_and_transform_points(gen):
    transform = se3_exp(torch.randn(5, 6, generator=gen, dtype=torch.float64))
    points = torch.randn(5, 7, 3, generator=gen, dtype=torch.float64)
    back = transform_points(invert_rigid(transform), transform_points(transform, points))
    # float64, two rigid transforms of O(1) points with translations up to ~3: ~10 eps64 * 3 ~ 1e-14
    assert torch.allclose(back, points, atol=1e-12)
    assert torch.allclose(invert_rigid(transform), torch.linalg.inv(transform), atol=1e-12)


def test_check_shape_wildcards():
    check_shape("x", torch.zeros(2, 5, 3), (..., 3))
    check_shape("x", torch.zeros(2, 5, 3), (-1, 5, 3))
    with pytest.raises(TypeError):
        check_shape("x", [1, 2, 3], (3,))
