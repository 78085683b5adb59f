"""Rigid-object models (docs/model.md §4, Eqs. 9-11): RT-NeRF, RT-NeRF without xi, RP-NeRF. One part: the object."""

from __future__ import annotations

import math

from narf.encodings import positional_encoding
from narf.fields.base import Field, FieldOutput
from narf.fields.common import RadianceHead


class RtNerf(Field):
    """RT-NeRF: density from gamma(u) in the object frame (60); colour from gamma(d_l) (24) and gamma(xi/pi) (48).

    Args:
        use_pose: False gives "RT-NeRF w/o xi".
    """

    def __init__(
        self, width: int = 256, latent_dim: int = 0, density_act: str = "leaky_backward", use_pose: bool = True
    ):
        super().__init__(1, latent_dim)
        self.use_pose = use_pose
        colour = {"dirs": 24, "pose": 48} if use_pose else {"dirs": 24}
        self.head = RadianceHead({"u": 60}, colour, width, latent_dim=latent_dim, density_act=density_act)

    def _forward(self, points, dirs, pose, x_local, d_local, u, in_box, z_s, z_a) -> FieldOutput:
        colour = {"dirs": positional_encoding(d_local[:, 0], 4)[None, :, None]}
        if self.use_pose:
            colour["pose"] = positional_encoding(pose.pose_features[:, 0] / math.pi, 4)[None, :, None]
        sigma, rgb = self.head({"u": positional_encoding(u[:, :, 0], 10)[None]}, colour, z_s, z_a)
        return FieldOutput(sigma[0], rgb[0], None)


class RpNerf(Field):
    """RP-NeRF: density from the global gamma(x / (1.25 s)) (60) and gamma(xi/pi) (48); colour from gamma(xi/pi),
    gamma(d) (world)."""

    def __init__(self, width: int = 256, latent_dim: int = 0, density_act: str = "leaky_backward"):
        super().__init__(1, latent_dim)
        self.head = RadianceHead(
            {"x": 60, "pose": 48}, {"pose": 48, "dirs": 24}, width, latent_dim=latent_dim, density_act=density_act
        )

    def _forward(self, points, dirs, pose, x_local, d_local, u, in_box, z_s, z_a) -> FieldOutput:
        x_hat = points / (1.25 * pose.reach[:, None, None])
        encoded_pose = positional_encoding(pose.pose_features[:, 0] / math.pi, 4)[None, :, None]
        density = {"x": positional_encoding(x_hat, 10)[None], "pose": encoded_pose}
        colour = {"pose": encoded_pose, "dirs": positional_encoding(dirs, 4)[None, :, None]}
        sigma, rgb = self.head(density, colour, z_s, z_a)
        return FieldOutput(sigma[0], rgb[0], None)
