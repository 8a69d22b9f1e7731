"""What a finished run leaves in its directory, written by a Lightning callback (not by the CLI).

`RunRecords` writes, when testing ends, on global rank 0, atomically (`rotlearn.io`):
- `metrics.json`: the final scalars of fitting and testing, the epochs and steps, the seeds, the
  task and head, which weights were tested, the best checkpoint's monitored value, whether the run
  `diverged`, and `test/err_vs_identity` (the test error over that of predicting the identity; a
  WARNING says when it stays above 0.9). Only what the config and seeds determine, so a rerun
  gives an identical file;
- `timing.json`: wall-clock seconds per epoch (from `EpochTimer`);
- `test_errors.json`: the per-sample test errors in degrees, where the model keeps them (box plots
  of paper Fig. 4);
- the hyper-parameters with the final errors, for TensorBoard's HPARAMS view (the errors are the
  last values of their scalar series, not scalars written again).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch
from lightning.pytorch.loggers import TensorBoardLogger

from rotlearn.io import write_json_atomic
from rotlearn.lit.callbacks import EpochLosses, EpochTimer

__all__ = ["RunRecords", "barely_learned", "divergence"]

log = logging.getLogger("rotlearn")


def divergence(
    metrics: dict[str, Any], train_losses: Sequence[float], factor: float = 100.0
) -> list[str]:
    """Why a run counts as diverged (an empty list: it did not).

    Two signs: the final test error (`test/err_mean`) is worse than predicting the identity
    (`test/identity_err_mean`), or the last epoch's mean training loss is more than `factor` times
    its lowest epoch value (for a lowest value <= 0, as a Bingham NLL can be: more than `factor`
    times its magnitude above it), or is not finite."""
    reasons = []
    err = metrics.get("test/err_mean")
    identity = metrics.get("test/identity_err_mean")
    if err is not None and identity is not None and not err <= identity:
        reasons.append(
            f"final test error {err:.2f} deg is worse than predicting the identity "
            f"({identity:.2f} deg)"
        )
    if train_losses:
        last, lowest = train_losses[-1], min(train_losses)
        grew = last > factor * lowest if lowest > 0 else last - lowest > factor * abs(lowest)
        if not math.isfinite(last) or grew:
            reasons.append(
                f"training loss grew from {lowest:.4g} (lowest epoch) to {last:.4g} (last epoch)"
            )
    return reasons


def barely_learned(metrics: dict[str, Any], ratio: float = 0.9) -> str | None:
    """Why a run that did not diverge still looks untrained (None: it learned): its final test
    error is above `ratio` times the error of predicting the identity. (A likelihood loss can
    fall steadily while the belief merely widens, leaving the rotations untrained.)"""
    err = metrics.get("test/err_mean")
    identity = metrics.get("test/identity_err_mean")
    if err is None or identity is None or not identity > 0 or not err > ratio * identity:
        return None
    return (
        f"final test error {err:.2f} deg is {err / identity:.2f}x that of predicting the "
        f"identity ({identity:.2f} deg): the model barely learned (try another optim.lr)"
    )


def _scalars(metrics: dict[str, Any]) -> dict[str, float]:
    return {k: float(v) for k, v in metrics.items() if torch.as_tensor(v).numel() == 1}


def _flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(tree, dict):
        out: dict[str, Any] = {}
        for k, v in tree.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    value = tree if isinstance(tree, (int, float, str, bool)) or tree is None else str(tree)
    return {prefix[:-1]: value}


def _find(trainer: pl.Trainer, kind: type) -> Any:
    found = [cb for cb in trainer.callbacks if isinstance(cb, kind)]
    return found[0] if found else None


class RunRecords(pl.Callback):
    """Write the run's records into `dirpath` when testing ends (module docstring).

    Args:
        dirpath: the run directory.

    Attributes:
        metrics: what was written to metrics.json (empty before the test ends).
    """

    def __init__(self, dirpath: str | Path) -> None:
        self.dirpath = Path(dirpath)
        self.metrics: dict[str, Any] = {}
        self._fit_metrics: dict[str, float] = {}

    def on_fit_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._fit_metrics = _scalars(trainer.callback_metrics)

    def on_test_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        metrics = {**self._fit_metrics, **_scalars(trainer.callback_metrics)}
        metrics = {k: v for k, v in metrics.items() if not k.startswith("time/")}
        metrics.update(self._facts(trainer, pl_module))
        reasons = divergence(metrics, getattr(_find(trainer, EpochLosses), "losses", []))
        for reason in reasons:
            log.warning("%s diverged: %s", self.dirpath, reason)
        metrics["diverged"] = bool(reasons)
        if "test/err_mean" in metrics and metrics.get("test/identity_err_mean"):
            metrics["test/err_vs_identity"] = (
                metrics["test/err_mean"] / metrics["test/identity_err_mean"]
            )
        untrained = None if reasons else barely_learned(metrics)
        if untrained:
            log.warning("%s: %s", self.dirpath, untrained)
        self.metrics = metrics
        if trainer.is_global_zero:
            self._write(trainer, pl_module, metrics)

    @staticmethod
    def _facts(trainer: pl.Trainer, pl_module: pl.LightningModule) -> dict[str, Any]:
        config = getattr(pl_module, "run_config", None) or {}
        facts: dict[str, Any] = {
            "epochs": trainer.current_epoch,
            "global_step": trainer.global_step,
            "seed": config.get("seed"),
            "data_seed": (config.get("data") or {}).get("seed"),
            "task": getattr(pl_module, "task", None),
            "tested_weights": "best" if trainer.ckpt_path else "last",
        }
        if facts["task"] == "rotation":
            facts["rep"] = getattr(pl_module.head, "name", None)
        checkpoints = trainer.checkpoint_callback
        if checkpoints and checkpoints.best_model_score is not None:  # best/val_err_mean, ...
            key = f"best/{checkpoints.monitor.replace('/', '_')}"
            facts[key] = float(checkpoints.best_model_score)
        return facts

    def _write(self, trainer: pl.Trainer, pl_module: pl.LightningModule, metrics: dict) -> None:
        timer = _find(trainer, EpochTimer)
        times = timer.epoch_times if timer else []
        steady = times[1:]  # the first epoch carries one-off start-up costs
        timing = {
            "epoch_times_s": times,
            "epoch_time_s": sum(steady) / len(steady) if steady else math.nan,
        }
        write_json_atomic(self.dirpath / "timing.json", timing)
        test_errors = getattr(pl_module, "test_errors", None)  # the auto-encoder has none
        if test_errors is not None:
            write_json_atomic(self.dirpath / "test_errors.json", test_errors.tolist())
        write_json_atomic(self.dirpath / "metrics.json", metrics)
        names = [k for k in metrics if "/err_" in k or "/recon_" in k]  # train/, val/, test/
        logged = set(self._fit_metrics) | set(_scalars(trainer.callback_metrics))
        unlogged = {k: metrics[k] for k in names if k not in logged}  # test/err_vs_identity
        params = _flatten(getattr(pl_module, "run_config", None) or {})
        for logger in trainer.loggers:
            if isinstance(logger, TensorBoardLogger):
                if unlogged:
                    logger.log_metrics(unlogged, step=trainer.global_step)
                _hparams_view(logger, params, names)
            else:
                logger.log_hyperparams(params)
            logger.finalize("success")


def _hparams_view(logger: TensorBoardLogger, params: dict[str, Any], names: list[str]) -> None:
    """The run in TensorBoard's HPARAMS view: its hyper-parameters and, as its metrics, the
    scalar series `names` (TensorBoard shows each series' last value: the final errors). Unlike
    `log_hyperparams(params, metrics)`, no scalar is written again (that would add a one-point
    card per metric above the training curves)."""
    from torch.utils.tensorboard.summary import hparams

    logger.hparams.update(params)  # also kept in <logger dir>/hparams.yaml
    experiment, start, end = hparams(logger._sanitize_params(params), dict.fromkeys(names, 0.0))
    writer = logger.experiment._get_file_writer()
    for summary in (experiment, start, end):
        writer.add_summary(summary)
