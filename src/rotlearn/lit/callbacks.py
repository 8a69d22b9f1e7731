"""Small training callbacks: epoch timing, per-epoch training loss, the record of a signal, the
data-dependent initialisation of a net, a model summary without empty columns, and a progress
bar that shows the training loss and the last validation error."""

from __future__ import annotations

import logging
import math
import signal
import time
from typing import Any

import lightning.pytorch as pl
import torch
from lightning.pytorch.callbacks import ModelSummary as LightningModelSummary
from lightning.pytorch.callbacks import TQDMProgressBar
from lightning.pytorch.utilities.exceptions import SIGTERMException
from lightning.pytorch.utilities.model_summary.model_summary import _format_summary_table

from rotlearn.trust import config_target

__all__ = [
    "DataDependentInit",
    "EpochLosses",
    "EpochTimer",
    "InterruptRecorder",
    "ModelSummary",
    "ProgressBar",
    "find_callback",
]

log = logging.getLogger("rotlearn")


def find_callback(trainer: pl.Trainer, kind: type) -> Any:
    """The trainer's first callback of type `kind`; None if it has none."""
    return next((cb for cb in trainer.callbacks if isinstance(cb, kind)), None)


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


class EpochLosses(pl.Callback):
    """The mean training loss of every finished epoch, in `losses` (one float per epoch).

    Batch losses are summed on the device (no host sync per step); the epoch's mean is read once,
    when its last batch is done: at the end-of-epoch validation (before `ModelCheckpoint` saves, so
    a checkpoint holds every finished epoch's loss) or else at `on_train_epoch_end`. The list is
    part of the checkpoint (`state_dict`), so a resumed run keeps the epochs before the resume.
    """

    def __init__(self) -> None:
        self.losses: list[float] = []
        self._sum: torch.Tensor | None = None
        self._count = 0

    def on_train_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._sum, self._count = None, 0

    def on_train_batch_end(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any, i: int
    ) -> None:
        loss = outputs.get("loss") if isinstance(outputs, dict) else outputs
        if isinstance(loss, torch.Tensor):
            loss = loss.detach().float()
            self._sum = loss if self._sum is None else self._sum + loss
            self._count += 1

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not trainer.sanity_checking and self._count == trainer.num_training_batches:
            self._close_epoch()

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._close_epoch()

    def running_mean(self) -> float | None:
        """The mean training loss of the epoch so far (None before its first batch): one host
        sync, for a reader that asks now and then (`ProgressBar`: once a second)."""
        return float(self._sum) / self._count if self._sum is not None and self._count else None

    def _close_epoch(self) -> None:
        if self._sum is not None and self._count:
            self.losses.append(float(self._sum) / self._count)
        self._sum, self._count = None, 0

    def state_dict(self) -> dict[str, Any]:
        return {"losses": list(self.losses)}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.losses = [float(v) for v in state_dict.get("losses", [])]


class InterruptRecorder(pl.Callback):
    """Turns SIGTERM and SIGINT during `fit`/`test` into a clean stop, and remembers which came.

    SIGTERM: Lightning's own handler sets `trainer.received_sigterm`, and its loops raise
    `SIGTERMException` at the next batch boundary. SIGINT (Ctrl+C): this callback routes the first
    one into the same flag, so the run also stops at a batch boundary instead of wherever the
    `KeyboardInterrupt` would land (a second Ctrl+C is Python's `KeyboardInterrupt` again, which
    Lightning catches too). Either way no checkpoint is half-written: `last.ckpt` stays what
    `ModelCheckpoint` saved at the end of the last finished epoch, the last safe point.

    After the stop `signal_name` is "SIGTERM" or "SIGINT" (None when no signal stopped the run);
    the CLI writes the run's status.json from it. Under SLURM, Lightning's SIGUSR1 requeue
    handler is left alone (this callback touches SIGINT only).
    """

    def __init__(self) -> None:
        self.signal_name: str | None = None
        self._previous: Any = None

    def setup(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        self.signal_name = None
        try:
            self._previous = signal.signal(signal.SIGINT, self._graceful_sigint(trainer))
        except ValueError:  # not the main thread: leave SIGINT to Python and Lightning
            self._previous = None

    def teardown(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
            self._previous = None

    def _graceful_sigint(self, trainer: pl.Trainer) -> Any:
        def handler(signum: int, frame: Any) -> None:
            self.signal_name = "SIGINT"
            signal.signal(signal.SIGINT, signal.default_int_handler)  # a second Ctrl+C is hard
            trainer._signal_connector.received_sigterm = True  # Lightning's graceful stop

        return handler

    def on_exception(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, exception: BaseException
    ) -> None:
        if isinstance(exception, KeyboardInterrupt):
            self.signal_name = "SIGINT"
        elif isinstance(exception, SIGTERMException) and self.signal_name is None:
            self.signal_name = "SIGTERM"


@config_target
class DataDependentInit(pl.Callback):
    """Before fitting, give a net with a data-dependent initialisation (`net.initialize_from`,
    e.g. `PointNet`) the first training batch, as the training step will see it.

    `RotationRegressor.configure_callbacks` adds it for such nets. It runs in `setup("fit")`:
    Lightning calls the callbacks' `setup` after the datamodule's and before the module's, all
    before it restores a resumed run's checkpoint (`_restore_modules_and_callbacks`) and before
    the strategy wraps the model (DDP broadcasts rank 0's weights then). So a resumed run keeps its
    saved weights, and every DDP rank draws the same, seeded first batch.

    The batch is made with the datamodule's `finish_batch` on the module's device and in its
    dtype (the data of the first training step), and moved to where the net's parameters are
    (the strategy moves the model to its device only after `setup`).
    """

    def setup(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        net = getattr(pl_module, "net", None)
        datamodule = trainer.datamodule
        if stage != "fit" or datamodule is None or not hasattr(net, "initialize_from"):
            return
        batch = next(iter(datamodule.train_dataloader()))
        if hasattr(datamodule, "finish_batch"):
            batch = datamodule.finish_batch(batch, pl_module.device, pl_module.dtype)
        else:  # a datamodule of another kind: its Lightning hook
            batch = datamodule.on_after_batch_transfer(batch, 0)
        parameter = next(net.parameters(), None)
        points = batch["input"]
        if parameter is not None:
            points = points.to(parameter.device)
        net.initialize_from(points)


class ModelSummary(LightningModelSummary):
    """Lightning's model summary (layers, parameters, mode; printed when fitting starts), without
    the FLOPs column and total where nothing was counted: Lightning counts FLOPs only for a
    module with an `example_input_array` and prints a column of zeros otherwise.

    `rotlearn.cli.training.build` puts it in place of Lightning's own summary when
    `trainer.enable_model_summary` is true.
    """

    @staticmethod
    def summarize(
        summary_data: list[tuple[str, list[str]]],
        total_parameters: int,
        trainable_parameters: int,
        model_size: float,
        total_training_modes: dict[str, int],
        total_flops: int,
        **summarize_kwargs: Any,
    ) -> None:
        if total_flops:
            LightningModelSummary.summarize(
                summary_data,
                total_parameters,
                trainable_parameters,
                model_size,
                total_training_modes,
                total_flops,
                **summarize_kwargs,
            )
            return
        columns = [(name, values) for name, values in summary_data if name != "FLOPs"]
        table = _format_summary_table(
            total_parameters, trainable_parameters, model_size, total_training_modes, 0, *columns
        )
        lines = [line for line in table.splitlines() if not line.rstrip().endswith("Total Flops")]
        log.info("model summary:\n%s", "\n".join(lines))


class ProgressBar(TQDMProgressBar):
    """Lightning's tqdm progress bar showing `loss`, the training loss (the epoch's running
    mean, read from `EpochLosses` at most once per `refresh_s` seconds: no host sync per step),
    and `val err`, the last validation median error in degrees; Lightning's `v_num` left out.

    `rotlearn.cli.training.build` puts it in place of Lightning's bar when
    `trainer.enable_progress_bar` is true.
    """

    def __init__(self, refresh_s: float = 1.0) -> None:
        super().__init__()
        self.refresh_s = float(refresh_s)
        self._loss: float | None = None
        self._val_err: float | None = None
        self._read_at = -math.inf

    def on_train_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        super().on_train_epoch_start(trainer, pl_module)
        self._read_at = -math.inf

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        super().on_validation_end(trainer, pl_module)
        value = trainer.callback_metrics.get("val/err_median")
        if value is not None and not trainer.sanity_checking:
            self._val_err = float(value)

    def get_metrics(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> dict[str, Any]:
        now = time.monotonic()
        losses = find_callback(trainer, EpochLosses)
        if losses is not None and now - self._read_at >= self.refresh_s:
            running = losses.running_mean()
            self._loss = running if running is not None else self._loss
            self._read_at = now
        shown: dict[str, Any] = {}
        if self._loss is not None:
            shown["loss"] = f"{self._loss:.4g}"
        if self._val_err is not None:
            shown["val err"] = f"{self._val_err:.3g} deg"
        return shown
