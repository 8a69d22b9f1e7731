"""Floor 3: training glue (LightningModules and callbacks)."""

from rotlearn.lit.callbacks import EpochTimer
from rotlearn.lit.regressor import RotationRegressor

__all__ = ["EpochTimer", "RotationRegressor"]
