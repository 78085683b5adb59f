"""The NARF autoencoder (docs/model.md §4, supplement §A): an image encoder and a latent-conditioned field
trained together on many people. Each training image is its own frame (its own pose); the encoder sees another
render of the same mesh (NARF's ``_view2`` copy) and its code z = [z_s, z_a] conditions the field for every ray
of the target image. Same losses as a per-subject fit (docs/model.md §6)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from fitting.config import FitConfig
from fitting.data import FitData, RayBatch
from fitting.losses import ray_loss
from fitting.trainer import Trainer
from narf.fields.encoder import ImageEncoder
from narf.rays import image_pixels, rays_from_pixels

#: Adam step size of ``refine_code`` on the code (the field's training rate, docs/model.md §4)
REFINE_LR = 0.01


@dataclass
class AutoencoderData(FitData):
    """FitData whose images each have their own pose, plus the encoder's inputs.

    Attributes:
        encoder_inputs: (N, 3, S, S) uint8 on the training device, the encoder's view of each training image's mesh.
    """

    encoder_inputs: torch.Tensor | None = None


def build_encoder(config) -> ImageEncoder:
    return ImageEncoder(config.model.latent_dim, image_size=128, base_channels=config.model.encoder_channels)


def encode(encoder: ImageEncoder, images_u8: torch.Tensor, gains: torch.Tensor | None = None) -> torch.Tensor:
    """(B, 3, S, S) uint8 -> (B, 2 L) codes; ``gains`` (B, 3) scale each image's channels first (clamped to 1)."""
    images = images_u8.float() / 255.0
    if gains is not None:
        images = scale_colours(images, gains[:, :, None, None])
    return encoder(images)


def scale_colours(colours: torch.Tensor, gains: torch.Tensor) -> torch.Tensor:
    """min(colours * gains, 1): the colour jitter of ``colour_gains``, one formula for encoder input and targets
    alike; ``gains`` broadcast against ``colours``."""
    return (colours * gains).clamp(max=1.0)


def colour_gains(n: int, strength: float, generator: torch.Generator) -> torch.Tensor | None:
    """(n, 3) channel gains g ~ U(1 - strength, 1 + strength), or None when ``strength`` is 0.

    Colour jitter (docs/model.md §4, beyond the paper): one gain per image and channel multiplies both the encoder's
    input and the target colours of that image's rays, so that the same mesh is seen in many colourings and the
    appearance code has to be read from the input rather than recalled for a known person. Black stays black.
    """
    if strength == 0:
        return None
    return 1.0 + strength * (2.0 * torch.rand(n, 3, generator=generator) - 1.0)


def refine_code(
    config: FitConfig,
    field,
    code: torch.Tensor,
    K: torch.Tensor,
    cam_from_world: torch.Tensor,
    pose,
    image: torch.Tensor,
    mask: torch.Tensor,
    steps: int,
    rays_per_step: int = 2048,
    seed: int = 0,
) -> torch.Tensor:
    """Test-time refinement of an encoded code on its input image (docs/model.md §4, beyond the paper).

    z_0 = the encoder's code; then ``steps`` Adam steps (``REFINE_LR``) on z alone minimise the training loss
    ``ray_loss`` over ``rays_per_step`` pixels of the input drawn uniformly, at the deterministic samples of a
    full-image render (``render.eval_coarse`` + ``eval_fine``: the estimator the scored renders use; random strata
    would shift the optimum by their noise); the field is not changed. The input must come with its camera and pose
    (a SURREAL frame, a ``render_128`` image), since the loss renders it.

    Args:
        code: (1, 2 L) encoder code. K (3, 3), cam_from_world (4, 4): the input's camera. pose: its one-frame
            PoseBatch. image (H, W, 3) in [0, 1], mask (H, W): the input and its silhouette.

    Returns:
        (1, 2 L) refined code (no gradient); ``code`` itself when ``steps`` is 0.
    """
    if steps < 0 or rays_per_step < 1:
        raise ValueError(f"refine_code: steps must be >= 0 and rays_per_step >= 1, got {steps}, {rays_per_step}")
    if steps == 0:
        return code
    device = code.device
    height, width = mask.shape
    origins, dirs = rays_from_pixels(
        K.float().to(device), cam_from_world.float().to(device), image_pixels(height, width, device)
    )
    count = height * width
    ones, frames = torch.ones(count, device=device), torch.zeros(count, dtype=torch.long, device=device)
    rgb, silhouette = image.reshape(-1, 3).float().to(device), mask.reshape(-1).float().to(device)
    pixels = RayBatch(origins, dirs, frames, rgb, silhouette, ones, frames)
    generator = torch.Generator(device).manual_seed(seed)
    latent = code.detach().clone().requires_grad_(True)
    optimiser = torch.optim.Adam([latent], lr=REFINE_LR)
    frozen = [p.requires_grad for p in field.parameters()]
    field.requires_grad_(False)
    samples = (config.render.eval_coarse, config.render.eval_fine)
    try:
        for _ in range(steps):
            batch = pixels.take(torch.randint(0, count, (rays_per_step,), device=device, generator=generator))
            loss, _ = ray_loss(config, field, batch, pose, generator, *samples, latent=latent, randomized=False)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
    finally:
        for parameter, flag in zip(field.parameters(), frozen):
            parameter.requires_grad_(flag)
    return latent.detach()


class AutoencoderTrainer(Trainer):
    """A Trainer whose field is conditioned on codes from a jointly trained image encoder."""

    def _build_extra_modules(self) -> None:
        self.encoder = build_encoder(self.config).to(self.device)
        self.encoder_inputs = self.fit_data.encoder_inputs

    def _parameter_groups(self) -> list[dict]:
        return [
            {"params": list(self.field.parameters())},
            {"params": list(self.encoder.parameters()), "lr": self.config.train.encoder_lr},
        ]

    def _extra_state(self) -> dict:
        return {"encoder": self.encoder.state_dict()}

    def _restore(self, state: dict) -> None:
        self.encoder.load_state_dict(state["encoder"])
        super()._restore(state)

    def train_step(self) -> tuple[float, float]:
        t = self.config.train
        batch = self.views.sample(
            t.images_per_step, t.rays_per_image, t.body_fraction, t.border_fraction, self.generator
        )
        images, batch.frames = torch.unique(batch.frames, return_inverse=True)
        gains = colour_gains(len(images), t.colour_jitter, self.generator)
        if gains is not None:
            gains = gains.to(self.device)
            batch.rgb = scale_colours(batch.rgb, gains[batch.frames])
        with self.autocast():
            latent = encode(self.encoder, self.encoder_inputs[images], gains)
            loss, colour = ray_loss(
                self.config,
                self.field,
                batch,
                self.views.poses.select(images),
                self.generator,
                self.config.render.train_coarse,
                self.config.render.train_fine,
                latent=latent,
            )
        return self.optimise(loss, colour)

    def _validation_latent(self, item: tuple) -> torch.Tensor | None:
        encoder_input = item[3]
        self.encoder.eval()
        with torch.no_grad():
            latent = encode(self.encoder, encoder_input[None].to(self.device))
        self.encoder.train()
        return latent
