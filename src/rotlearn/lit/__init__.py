"""Floor 3: training glue (LightningModules and callbacks)."""

from rotlearn.extras import require

require("train", "rotlearn.lit")

from rotlearn.lit.autoencoder import AutoEncoderModule, load_autoencoder
from rotlearn.lit.boundary import CheckpointStateGuard, RunCheckpointIO
from rotlearn.lit.calibration import PostHocCalibration
from rotlearn.lit.callbacks import (
    EpochLosses,
    EpochTimer,
    InterruptRecorder,
    ModelSummary,
    ProgressBar,
    find_callback,
)
from rotlearn.lit.records import RunRecords, barely_learned, divergence
from rotlearn.lit.regressor import RotationRegressor
from rotlearn.lit.tensorboard import TensorBoardRunLogger

__all__ = [
    "AutoEncoderModule",
    "CheckpointStateGuard",
    "EpochLosses",
    "EpochTimer",
    "InterruptRecorder",
    "ModelSummary",
    "PostHocCalibration",
    "ProgressBar",
    "RotationRegressor",
    "RunCheckpointIO",
    "RunRecords",
    "TensorBoardRunLogger",
    "barely_learned",
    "divergence",
    "find_callback",
    "load_autoencoder",
]
