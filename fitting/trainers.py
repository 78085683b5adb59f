"""One map from what a run fits (its kind and its model's family, ``narf.fields.MODEL_SPECS``) to the trainer class
that fits it."""

from __future__ import annotations

from fitting.autoencoder import AutoencoderTrainer
from fitting.cnn_trainer import CnnAutoencoderTrainer, CnnTrainer
from fitting.config import FitConfig
from fitting.trainer import Trainer
from narf.fields import model_spec

#: (config.kind, model family) -> trainer class.
TRAINERS: dict[tuple[str, str], type[Trainer]] = {
    ("subject", "field"): Trainer,
    ("subject", "image"): CnnTrainer,
    ("autoencoder", "field"): AutoencoderTrainer,
    ("autoencoder", "image"): CnnAutoencoderTrainer,
    ("rigid", "rigid"): Trainer,
}


def trainer_class(config: FitConfig) -> type[Trainer]:
    """The trainer of ``config``'s kind and model (``validate_config`` already refused other pairs)."""
    return TRAINERS[(config.kind, model_spec(config.model.name).family)]
