"""Floor 3: training glue (LightningModules and callbacks)."""

from rotlearn.extras import require

require("train", "rotlearn.lit")

from rotlearn.lit.autoencoder import AutoEncoderModule, load_autoencoder
from rotlearn.lit.calibration import TemperatureScaling
from rotlearn.lit.callbacks import (
    EpochLosses,
    EpochTimer,
    InterruptRecorder,
    ModelSummary,
    ProgressBar,
)
from rotlearn.lit.records import RunRecords, barely_learned, divergence
from rotlearn.lit.regressor import RotationRegressor
from rotlearn.lit.tensorboard import TensorBoardRunLogger

__all__ = [
    "AutoEncoderModule",
    "EpochLosses",
    "EpochTimer",
    "InterruptRecorder",
    "ModelSummary",
    "ProgressBar",
    "RotationRegressor",
    "RunRecords",
    "TemperatureScaling",
    "TensorBoardRunLogger",
    "barely_learned",
    "divergence",
    "load_autoencoder",
]
