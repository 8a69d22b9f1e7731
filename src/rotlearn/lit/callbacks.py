"""Small training callbacks."""

from __future__ import annotations

import time

import lightning.pytorch as pl

from rotlearn.trust import config_target

__all__ = ["EpochTimer"]


@config_target
class EpochTimer(pl.Callback):
    """Wall-clock seconds per epoch (training and its validation), logged as `time/epoch_s`.

    (Lightning runs the end-of-epoch validation before `on_train_epoch_end`.) `epoch_times` keeps
    every epoch's duration for the run's `metrics.json`.
    """

    def __init__(self) -> None:
        self.epoch_times: list[float] = []
        self._start = 0.0

    def on_train_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._start = time.perf_counter()

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self.epoch_times.append(time.perf_counter() - self._start)
        pl_module.log("time/epoch_s", self.epoch_times[-1], on_step=False, on_epoch=True)
