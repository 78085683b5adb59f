"""Rigid-object models (docs/model.md §4, Eqs. 9-11): RT-NeRF, RT-NeRF without xi, RP-NeRF. One part: the object."""

from __future__ import annotations

import math

from narf.encodings import (
    DIRECTION_WIDTH,
    POINT_WIDTH,
    POSE_FREQS,
    XI_WIDTH,
    positional_encoding,
)
from narf.fields.base import Field, FieldInputs, FieldOutput
from narf.fields.common import RadianceHead


class RtNerf(Field):
    """RT-NeRF: density from gamma(u) in the object frame (60); colour from gamma(d_l) (24) and gamma(xi/pi) (48).

    Args:
        use_pose: False gives "RT-NeRF w/o xi".
    """

    def __init__(
        self,
        width: int = 256,
        latent_dim: int = 0,
        density_act: str = "leaky_backward",
        use_pose: bool = True,
        appearance_dim: int = 0,
    ):
        super().__init__(1, latent_dim, appearance_dim)
        self.use_pose = use_pose
        colour = {"dirs": DIRECTION_WIDTH, "pose": XI_WIDTH} if use_pose else {"dirs": DIRECTION_WIDTH}
        self.head = RadianceHead(
            {"u": POINT_WIDTH},
            colour,
            width,
            latent_dim=latent_dim,
            density_act=density_act,
            appearance_dim=appearance_dim,
        )

    def _forward(self, inputs: FieldInputs) -> FieldOutput:
        _, _, pose, _, d_local, u, _, z_s, z_a = inputs
        colour = {"dirs": self.encode_dirs(d_local[:, 0])[None, :, None]}
        if self.use_pose:
            colour["pose"] = self.encode_pose(pose.pose_features[:, 0])[None, :, None]
        sigma, rgb = self.head({"u": self.encode_points(u[:, :, 0])[None]}, colour, z_s, z_a)
        return FieldOutput(sigma[0], rgb[0], None)


class RpNerf(Field):
    """RP-NeRF: density from the global gamma(x / (1.25 s)) (60) and gamma(xi/pi) (48); colour from gamma(xi/pi),
    gamma(d) (world)."""

    pose_in_density = True

    def __init__(
        self, width: int = 256, latent_dim: int = 0, density_act: str = "leaky_backward", appearance_dim: int = 0
    ):
        super().__init__(1, latent_dim, appearance_dim)
        self.head = RadianceHead(
            {"x": POINT_WIDTH, "pose": XI_WIDTH},
            {"pose": XI_WIDTH, "dirs": DIRECTION_WIDTH},
            width,
            latent_dim=latent_dim,
            appearance_dim=appearance_dim,
            density_act=density_act,
        )

    def _forward(self, inputs: FieldInputs) -> FieldOutput:
        points, dirs, pose, _, _, _, _, z_s, z_a = inputs
        x_hat = points / (1.25 * pose.reach[:, None, None])
        encoded_pose = positional_encoding(pose.pose_features[:, 0] / math.pi, POSE_FREQS)[None, :, None]
        density = {"x": self.encode_points(x_hat)[None], "pose": encoded_pose}
        colour = {"pose": encoded_pose, "dirs": self.encode_dirs(dirs)[None, :, None]}
        sigma, rgb = self.head(density, colour, z_s, z_a)
        return FieldOutput(sigma[0], rgb[0], None)
