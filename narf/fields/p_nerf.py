"""P-NeRF: a single NeRF conditioned on all part poses (docs/model.md §4, eqs. B-D)."""

from __future__ import annotations

import math

from narf.encodings import (
    DIRECTION_WIDTH,
    POINT_WIDTH,
    POSE_FREQS,
    XI_WIDTH,
    positional_encoding,
    zeta_width,
)
from narf.fields.base import Field, FieldInputs, FieldOutput
from narf.fields.common import RadianceHead


class PNerf(Field):
    """Density from gamma(x_hat) (60), {gamma(xi_i/pi)} (P*48), gamma(zeta) (152) with x_hat = (x - b)/(1.25 s);
    colour from {gamma(xi_i/pi)} (if ``pose_in_color``, eq. D) and gamma(d) (24, world directions).

    ``pose_in_color=False`` reproduces the supplement's 0.85M parameter count (upstream).
    """

    pose_in_density = True

    def __init__(
        self,
        n_parts: int = 19,
        width: int = 256,
        latent_dim: int = 0,
        density_act: str = "leaky_backward",
        pose_in_color: bool = True,
        appearance_dim: int = 0,
    ):
        super().__init__(n_parts, latent_dim, appearance_dim)
        self.pose_in_color = pose_in_color
        colour = {"pose": XI_WIDTH * n_parts, "dirs": DIRECTION_WIDTH} if pose_in_color else {"dirs": DIRECTION_WIDTH}
        density = {"x": POINT_WIDTH, "pose": XI_WIDTH * n_parts, "zeta": zeta_width(n_parts)}
        self.head = RadianceHead(
            density, colour, width, latent_dim=latent_dim, appearance_dim=appearance_dim, density_act=density_act
        )

    def _forward(self, inputs: FieldInputs) -> FieldOutput:
        points, dirs, pose, _, _, _, _, z_s, z_a = inputs
        pelvis = pose.world_from_part[:, 0, :3, 3]
        x_hat = (points - pelvis[:, None]) / (1.25 * pose.reach[:, None, None])
        encoded_pose = positional_encoding(pose.pose_features / math.pi, POSE_FREQS).flatten(1)[None, :, None]
        density = {
            "x": self.encode_points(x_hat)[None],
            "pose": encoded_pose,
            "zeta": self.zeta_encoding(pose)[None],
        }
        colour = {"dirs": self.encode_dirs(dirs)[None, :, None]}
        if self.pose_in_color:
            colour["pose"] = encoded_pose
        sigma, rgb = self.head(density, colour, z_s, z_a)
        return FieldOutput(sigma[0], rgb[0], None)
