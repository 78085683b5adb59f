"""The se(3) logarithm of the paper's pose features (textbook form, docs/model.md §1), exponentials and shape checks.

Pure torch, batched over leading dimensions. Transforms are 4x4 homogeneous matrices named ``<dst>_from_<src>``.
The logarithm stays here because it is the paper's definition (tested against kornia's ``Se3.log``). From kornia
it uses the skew matrices (``So3.hat`` / ``So3.vee``) and ``Se3.exp`` behind ``se3_exp`` (which only reorders the
twist). The rest of the code builds rigid transforms with ``narf.kinematics.rigid_from_rotvec_translation`` and
plain matrix algebra; kornia's ``axis_angle_to_rotation_matrix``, ``inverse_transformation`` and
``transform_points`` are the tests' references for those, not used by the product.
"""

from __future__ import annotations

import math

import torch
from kornia.geometry.liegroup import Se3, So3

_SMALL_ANGLE = 1e-3  # below: Taylor forms
_NEAR_PI = math.pi / 2  # above: axis from the symmetric part of R


def check_shape(name: str, tensor: torch.Tensor, shape: tuple) -> None:
    """Raise a ValueError naming ``name`` unless ``tensor`` has ``shape``.

    ``shape`` may start with ``...`` (any leading dims); ``-1`` matches any size.
    """
    if not isinstance(tensor, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(tensor).__name__}")
    dims = tuple(tensor.shape)
    want = tuple(shape)
    if want and want[0] is Ellipsis:
        want = want[1:]
        ok = len(dims) >= len(want) and all(w == -1 or w == d for w, d in zip(want, dims[len(dims) - len(want) :]))
    else:
        ok = len(dims) == len(want) and all(w == -1 or w == d for w, d in zip(want, dims))
    if not ok:
        pretty = ", ".join("..." if w is Ellipsis else ("*" if w == -1 else str(w)) for w in shape)
        raise ValueError(f"{name}: expected shape ({pretty}), got {dims}")


def so3_log(rotation: torch.Tensor) -> torch.Tensor:
    """Rotation vector of a rotation matrix (the so(3) logarithm).

    theta = arccos((tr R - 1) / 2) (clamped); omega = theta / (2 sin theta) vee(R - R^T); Taylor form near
    theta = 0 and, above pi/2, the axis from the symmetric part ``(R + R^T)/2 - cos(theta) I = (1 - cos) n n^T``
    with the sign of vee(R - R^T).

    Args:
        rotation: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) rotation vectors with norm in [0, pi].
    """
    check_shape("rotation", rotation, (..., 3, 3))
    trace = rotation[..., 0, 0] + rotation[..., 1, 1] + rotation[..., 2, 2]
    cos = ((trace - 1) / 2).clamp(-1.0, 1.0)
    theta = torch.arccos(cos)
    anti = So3.vee(rotation - rotation.transpose(-1, -2))  # = 2 sin(theta) n
    sin = torch.sin(theta)
    small = theta < _SMALL_ANGLE
    factor = torch.where(small, 0.5 + theta**2 / 12, theta / (2 * torch.where(small, torch.ones_like(sin), sin)))
    omega_regular = factor[..., None] * anti
    # Near pi: n n^T from the symmetric part; take the column with the largest diagonal.
    eye = torch.eye(3, dtype=rotation.dtype, device=rotation.device)
    sym = (rotation + rotation.transpose(-1, -2)) / 2 - cos[..., None, None] * eye
    sym = sym / (1 - cos).clamp_min(1e-12)[..., None, None]
    diag = torch.diagonal(sym, dim1=-2, dim2=-1)
    col = diag.argmax(dim=-1)
    axis = torch.gather(sym, -1, col[..., None, None].expand(*col.shape, 3, 1))[..., 0]
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    sign = torch.where((axis * anti).sum(-1) < 0, -1.0, 1.0).to(rotation.dtype)
    omega_pi = (sign * theta)[..., None] * axis
    return torch.where((theta > _NEAR_PI)[..., None], omega_pi, omega_regular)


def _v_inverse(omega: torch.Tensor) -> torch.Tensor:
    """V^-1 = I - Omega/2 + (1/theta^2) (1 - theta sin / (2 (1 - cos))) Omega^2, Taylor 1/12 near 0."""
    theta = omega.norm(dim=-1)
    small = theta < _SMALL_ANGLE
    safe = torch.where(small, torch.ones_like(theta), theta)
    coeff = (1 - safe * torch.sin(safe) / (2 * (1 - torch.cos(safe)))) / safe**2
    coeff = torch.where(small, 1.0 / 12 + theta**2 / 720, coeff)
    skew = So3.hat(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device)
    return eye - skew / 2 + coeff[..., None, None] * (skew @ skew)


def se3_log(transform: torch.Tensor) -> torch.Tensor:
    """se(3) logarithm xi = [omega; u] of a rigid transform [R | t], with u = V^-1 t.

    Args:
        transform: (..., 4, 4) rigid transforms.

    Returns:
        (..., 6) twists, rotation part first.
    """
    check_shape("transform", transform, (..., 4, 4))
    omega = so3_log(transform[..., :3, :3])
    u = (_v_inverse(omega) @ transform[..., :3, 3:4])[..., 0]
    return torch.cat([omega, u], dim=-1)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """se(3) exponential of twists ordered as ``se3_log`` returns them, [omega; u] -> [exp(Omega) | V u].

    kornia's ``Se3.exp`` orders the twist (translation part, rotation part); this only swaps the halves.

    Args:
        xi: (..., 6) twists, rotation part first.

    Returns:
        (..., 4, 4) rigid transforms.
    """
    check_shape("xi", xi, (..., 6))
    matrix = Se3.exp(torch.cat([xi[..., 3:], xi[..., :3]], dim=-1)).matrix()
    # kornia keeps the rotation as an nn.Parameter, so the matrix would carry a graph even for a plain xi
    return matrix if xi.requires_grad else matrix.detach()
