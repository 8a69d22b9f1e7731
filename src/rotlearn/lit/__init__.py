"""Floor 3: training glue (LightningModules and callbacks)."""

from rotlearn.lit.autoencoder import AutoEncoderModule, load_autoencoder
from rotlearn.lit.callbacks import EpochTimer
from rotlearn.lit.regressor import RotationRegressor

__all__ = ["AutoEncoderModule", "EpochTimer", "RotationRegressor", "load_autoencoder"]
