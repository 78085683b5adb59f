"""Lambertian shading under a learned world lighting (docs/model.md §3, *Shading*).

Under distant lights fixed in the world, a matte surface point of albedo a and world normal n shows the colour
c = a E(n), where the irradiance E is the lighting's cosine-weighted integral over the hemisphere around n. E is
smooth: the real spherical harmonics of degree <= 2 hold it to about 1 % on average (Ramamoorthi & Hanrahan 2001,
"An Efficient Representation for Irradiance Environment Maps"), so the model learns E as 9 coefficients a colour
channel: E_c(n) = sum_k L_ck Y_k(n).
"""

from __future__ import annotations

import math

import torch

#: the constant factors of the real spherical harmonics Y_00, Y_1m, Y_2m (the normalisation of the unit sphere)
SH_C0 = 0.5 / math.sqrt(math.pi)
SH_C1 = math.sqrt(3 / (4 * math.pi))
SH_C2 = 0.5 * math.sqrt(15 / math.pi)
SH_C20 = 0.25 * math.sqrt(5 / math.pi)
#: the basis's size for degree <= 2
SH_TERMS = 9


def sh_basis(normals: torch.Tensor) -> torch.Tensor:
    """The 9 real spherical harmonics of degree <= 2 at unit vectors, in the order Y_00, Y_1-1, Y_10, Y_11, Y_2-2,
    Y_2-1, Y_20, Y_21, Y_22:

        C0, C1 y, C1 z, C1 x, C2 x y, C2 y z, C20 (3 z^2 - 1), C2 x z, C2 (x^2 - y^2) / 2

    Args:
        normals: (..., 3) unit vectors (x, y, z).

    Returns:
        (..., 9).
    """
    x, y, z = normals.unbind(-1)
    return torch.stack(
        [
            torch.full_like(x, SH_C0),
            SH_C1 * y,
            SH_C1 * z,
            SH_C1 * x,
            SH_C2 * x * y,
            SH_C2 * y * z,
            SH_C20 * (3 * z * z - 1),
            SH_C2 * x * z,
            0.5 * SH_C2 * (x * x - y * y),
        ],
        dim=-1,
    )


def constant_lighting(channels: int = 3) -> torch.Tensor:
    """Coefficients (channels, 9) of the irradiance E = 1 in every direction (the shading that leaves the albedo)."""
    coefficients = torch.zeros(channels, SH_TERMS)
    coefficients[:, 0] = 1 / SH_C0
    return coefficients


def irradiance(normals: torch.Tensor, coefficients: torch.Tensor) -> torch.Tensor:
    """E_c(n) = sum_k L_ck Y_k(n), clamped at 0 (light is never negative; a fitted degree-2 expansion can dip below
    it opposite a strong light).

    Args:
        normals: (..., 3) unit vectors. coefficients: (C, 9).

    Returns:
        (..., C).
    """
    return (sh_basis(normals) @ coefficients.T).clamp_min(0)
