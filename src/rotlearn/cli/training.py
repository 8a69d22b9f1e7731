"""Train and test one run of a composed config: `build` and `train`, run by `rotlearn-train`
(`rotlearn.cli.train`, the entry point, which also re-exports them).

Every component comes from the Hydra config with `hydra.utils.instantiate` (`build`); every file
goes below `paths.output_dir` (Hydra's run directory), the records written by
`rotlearn.lit.RunRecords`. Resuming is `rotlearn.cli.resume`. See conf/train.yaml; the config is
validated and the model built by `rotlearn.config`.
"""

from __future__ import annotations

import contextlib
import logging
import math
import signal
import sys
import warnings
from pathlib import Path
from typing import Any

import hydra
import lightning.pytorch as pl
import torch
from hydra.errors import InstantiationException
from omegaconf import DictConfig, OmegaConf

from rotlearn import config
from rotlearn.checkpoint import load_checkpoint
from rotlearn.cli.callbacks import record_job
from rotlearn.cli.resume import checkpoint_to_resume
from rotlearn.errors import ConfigError
from rotlearn.lit import (
    EpochLosses,
    InterruptRecorder,
    ModelSummary,
    RunRecords,
    TemperatureScaling,
)

__all__ = ["ConfigError", "RunInterrupted", "build", "report", "train"]

log = logging.getLogger("rotlearn")

# Lightning's advice that does not apply: batches are drawn on the device (no loader workers),
# and scalars are logged once per epoch on purpose.
for _pattern in (".*does not have many workers.*", ".*smaller than the logging interval.*"):
    warnings.filterwarnings("ignore", _pattern)
# Lightning's own use of a torch API that torch deprecates (its loops flatten every batch), which
# nobody but Lightning can act on.
warnings.filterwarnings(
    "ignore",
    message=r"`isinstance\(treespec, LeafSpec\)` is deprecated",
    category=FutureWarning,
    module=r"lightning\.pytorch\.utilities\._pytree",
)


class _WithoutCloudTips(logging.Filter):
    """Drops Lightning's tips to install its cloud services' packages (litlogger, litmodels),
    printed on every run; Lightning has no switch (Lightning-AI/pytorch-lightning#21294)."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        advert = "litlogger" in message or "litmodels" in message
        return not (message.startswith("💡 Tip:") and advert)


logging.getLogger("lightning.pytorch.utilities.rank_zero").addFilter(_WithoutCloudTips())


def _instantiate_all(cfg: DictConfig, key: str) -> list[Any]:
    node = OmegaConf.select(cfg, key) or {}
    return [_instantiate(cfg, f"{key}.{name}") for name in node]


def _instantiate(cfg: DictConfig, key: str, **kwargs: Any) -> Any:
    try:
        return hydra.utils.instantiate(OmegaConf.select(cfg, key), **kwargs)
    except InstantiationException as exc:  # Hydra wraps what the constructor raised
        if isinstance(exc.__cause__, ConfigError):
            raise exc.__cause__.within(key) from None
        raise


def build(cfg: DictConfig) -> tuple[pl.LightningModule, pl.LightningDataModule, pl.Trainer]:
    """Model, datamodule and trainer for a composed config: `rotlearn.config.build` (validated,
    seeded; the model with its net, head, loss, optimizer and scheduler, or the auto-encoder)
    and a trainer with the configured callbacks plus the run's record keeping (`RunRecords`,
    `InterruptRecorder`, `EpochLosses`), whatever `callbacks=` says; `calibrate: true` adds the
    post-hoc temperature fit (`rotlearn.lit.calibration.TemperatureScaling`), and
    `trainer.enable_model_summary` gives rotlearn's `ModelSummary`."""
    model, datamodule = config.build(cfg)
    callbacks = _instantiate_all(cfg, "callbacks")
    callbacks += [RunRecords(cfg.paths.output_dir), InterruptRecorder(), EpochLosses()]
    if OmegaConf.select(cfg, "calibrate", default=False):
        callbacks.append(TemperatureScaling(cfg.paths.output_dir))
    if OmegaConf.select(cfg, "trainer.enable_model_summary", default=True):
        callbacks.append(ModelSummary())  # Lightning's, without its column of zero FLOPs
    trainer = _instantiate(
        cfg,
        "trainer",
        callbacks=callbacks,
        logger=_instantiate_all(cfg, "logger") or False,
        enable_model_summary=False,  # the summary is the callback above
    )
    return model, datamodule, trainer


class RunInterrupted(SystemExit):
    """A signal stopped the run; the exit code is the shell's 128 + signal number (SIGTERM 143,
    SIGINT 130). `status` is what `train` wrote into the run's status.json."""

    def __init__(self, run_dir: Path, signal_name: str, last_epoch: int | None) -> None:
        self.run_dir, self.signal_name, self.last_epoch = run_dir, signal_name, last_epoch
        self.resume_command = f"rotlearn-train ckpt_path={run_dir.resolve()}"
        after = f"after epoch {last_epoch}" if last_epoch is not None else "before its first epoch"
        self.message = f"stopped by {signal_name} {after}; resume: {self.resume_command}"
        super().__init__(128 + int(signal.Signals[signal_name]))

    @property
    def status(self) -> dict[str, Any]:
        return {
            "signal": self.signal_name,
            "last_finished_epoch": self.last_epoch,
            "resume_command": self.resume_command,
            "error": self.message,
        }


def _last_finished_epoch(run_dir: Path, trainer: pl.Trainer) -> int | None:
    """The epoch (0-based, as Lightning counts) that `<run_dir>/checkpoints/last.ckpt` ends."""
    try:
        return int(load_checkpoint(run_dir)["epoch"])
    except (OSError, RuntimeError, KeyError, ValueError):
        done = trainer.fit_loop.epoch_progress.current.completed
        return done - 1 if done else None


@contextlib.contextmanager
def _interruptions_recorded(trainer: pl.Trainer, run_dir: Path):
    """Turn a stop by SIGTERM or SIGINT (seen by the trainer's `InterruptRecorder`) into a
    status.json with status INTERRUPTED in `run_dir` and a `RunInterrupted` exit; anything else
    propagates unchanged."""
    try:
        yield
    except (SystemExit, KeyboardInterrupt):
        recorders = [cb for cb in trainer.callbacks if isinstance(cb, InterruptRecorder)]
        name = recorders[0].signal_name if recorders else None
        if name is None:
            raise
        stop = RunInterrupted(run_dir, name, _last_finished_epoch(run_dir, trainer))
        if trainer.is_global_zero:
            record_job(run_dir, "INTERRUPTED", **stop.status)
        log.warning("%s: %s", run_dir, stop.message)
        raise stop from None


def train(cfg: DictConfig) -> dict[str, Any]:
    """Fit and test the run of `cfg` in `cfg.paths.output_dir`; returns its metrics.

    The config is validated by `build`, before anything is trained; the records (metrics.json,
    timing.json, test_errors.json) are written by `RunRecords` when testing ends. A SIGTERM or
    SIGINT during `fit` or `test` stops the run at a batch boundary: `checkpoints/last.ckpt` stays
    the end of the last finished epoch, `status.json` says INTERRUPTED (signal, that epoch, the
    resume command) and `RunInterrupted` exits 143 (SIGTERM) or 130 (SIGINT)."""
    run_dir = Path(cfg.paths.output_dir)
    resume = checkpoint_to_resume(cfg, run_dir)
    torch.set_float32_matmul_precision(cfg.float32_matmul_precision)
    model, datamodule, trainer = build(cfg)
    with _interruptions_recorded(trainer, run_dir):
        trainer.fit(model, datamodule=datamodule, ckpt_path=resume, weights_only=True)
        best = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
        ckpt_path = best if cfg.test_ckpt == "best" and best else None
        trainer.test(
            model, datamodule=datamodule, ckpt_path=ckpt_path, verbose=False, weights_only=True
        )
    return next(cb for cb in trainer.callbacks if isinstance(cb, RunRecords)).metrics


def report(cfg: DictConfig, metrics: dict[str, Any]) -> None:
    """Log a finished run's test errors, its directory and how to open TensorBoard on it."""
    run_dir = Path(cfg.paths.output_dir)
    try:
        shown = run_dir.resolve().relative_to(Path.cwd())
    except ValueError:
        shown = run_dir
    tensorboard = Path(sys.executable).parent / "tensorboard"
    tb = str(tensorboard) if tensorboard.exists() else "tensorboard"
    with contextlib.suppress(ValueError):
        tb = str(Path(tb).relative_to(Path.cwd()))
    if metrics.get("task") == "autoencoder":
        log.info(
            "test reconstruction error (auto-encoder, %s weights): mean L1 %.4f",
            metrics.get("tested_weights"),
            metrics.get("test/recon_mean", math.nan),
        )
    else:
        log.info(
            "test error (%s head, %s weights): mean %.3f deg, median %.3f deg, p90 %.3f deg",
            metrics.get("rep"),
            metrics.get("tested_weights"),
            metrics.get("test/err_mean", math.nan),
            metrics.get("test/err_median", math.nan),
            metrics.get("test/err_p90", math.nan),
        )
        log.info(
            'baseline "predict identity": mean %.3f deg, median %.3f deg',
            metrics.get("test/identity_err_mean", math.nan),
            metrics.get("test/identity_err_median", math.nan),
        )
    log.info("run directory: %s (metrics.json, checkpoints/, tensorboard/)", shown)
    log.info("open TensorBoard: %s --logdir %s", tb, shown)
