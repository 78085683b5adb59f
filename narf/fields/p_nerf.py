"""P-NeRF: a single NeRF conditioned on all part poses (docs/model.md §4, eqs. B-D)."""

from __future__ import annotations

import math

from narf.encodings import positional_encoding
from narf.fields.base import Field, FieldOutput
from narf.fields.common import RadianceHead


class PNerf(Field):
    """Density from gamma(x_hat) (60), {gamma(xi_i/pi)} (P*48), gamma(zeta) (152) with x_hat = (x - b)/(1.25 s);
    colour from {gamma(xi_i/pi)} (if ``pose_in_color``, eq. D) and gamma(d) (24, world directions).

    ``pose_in_color=False`` reproduces the supplement's 0.85M parameter count (upstream).
    """

    def __init__(
        self,
        n_parts: int = 19,
        width: int = 256,
        latent_dim: int = 0,
        density_act: str = "leaky_backward",
        pose_in_color: bool = True,
    ):
        super().__init__(n_parts, latent_dim)
        self.pose_in_color = pose_in_color
        colour = {"pose": 48 * n_parts, "dirs": 24} if pose_in_color else {"dirs": 24}
        self.head = RadianceHead(
            {"x": 60, "pose": 48 * n_parts, "zeta": 152}, colour, width, latent_dim=latent_dim, density_act=density_act
        )

    def _forward(self, points, dirs, pose, x_local, d_local, u, in_box, z_s, z_a) -> FieldOutput:
        pelvis = pose.world_from_part[:, 0, :3, 3]
        x_hat = (points - pelvis[:, None]) / (1.25 * pose.reach[:, None, None])
        encoded_pose = positional_encoding(pose.pose_features / math.pi, 4).flatten(1)[None, :, None]
        density = {
            "x": positional_encoding(x_hat, 10)[None],
            "pose": encoded_pose,
            "zeta": self.zeta_encoding(pose)[None],
        }
        colour = {"dirs": positional_encoding(dirs, 4)[None, :, None]}
        if self.pose_in_color:
            colour["pose"] = encoded_pose
        sigma, rgb = self.head(density, colour, z_s, z_a)
        return FieldOutput(sigma[0], rgb[0], None)
