"""What a finished run leaves in its directory, written by a Lightning callback (not by the CLI).

`RunRecords` writes, when testing ends, on global rank 0, atomically (`rotlearn.io`):
- `metrics.json`: the final scalars of fitting and testing (`val/*`, `train/*`: the last
  epoch's), the epochs and steps, the seeds, the task and head, the belief's temperature the
  test used, which weights were tested and the epochs they had trained (`tested_epochs`: fewer
  than `epochs` where `test_ckpt=best` chose an earlier epoch), the best
  checkpoint's monitored value, whether the run `diverged`, and `test/err_vs_identity` (the test
  error over that of predicting the identity; a WARNING says when it stays above 0.9), then the
  command's own `facts` (`rotlearn-eval`: the checkpoint). Only what the config and seeds
  determine, so a rerun gives an identical file; written once;
- `timing.json`: wall-clock seconds per epoch (from `EpochTimer`);
- `test_errors.json`: the per-sample test errors in degrees, where the model keeps them (box plots
  of paper Fig. 4);
- to each logger: the run's HPARAMS record (`hparams`: what the run set, `rotlearn.report.
  identity.hparams_record`), and, in a `TensorBoardRunLogger`, the headline results
  (`HEADLINE_RESULTS` that the run has: test error mean and median, error vs identity, the
  belief's NLL and ECE, each OOD score's AUROC) as the HPARAMS view's metrics and points in the
  test sub-run, with every one-shot result in one text table (`rotlearn.report.tables.
  results_table`).

One-shot results come from `trainer.callback_metrics` (what the module logged when testing,
never as a scalar series) and from the `results` dict of the callbacks before this one (the OOD
evaluation's AUROCs); `rotlearn.cli.training.build` puts `RunRecords` after every other callback.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch

from rotlearn.io import write_json_atomic
from rotlearn.lit.callbacks import EpochLosses, EpochTimer, find_callback
from rotlearn.report.tables import results_table

__all__ = ["HEADLINE_RESULTS", "RunRecords", "barely_learned", "divergence"]

log = logging.getLogger("rotlearn")

# What TensorBoard's HPARAMS view compares runs by (those a run has), plus ood/auroc_<score>.
HEADLINE_RESULTS = ("test/err_mean", "test/err_median", "test/err_vs_identity", "test/nll",
                    "test/ece", "test/recon_mean")  # fmt: skip


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


class RunRecords(pl.Callback):
    """Write the run's records into `dirpath` when testing ends (module docstring).

    Args:
        dirpath: the run directory.
        hparams: the run's HPARAMS record ({key: bool, number or text}); None: its seed alone.

    Attributes:
        metrics: what was written to metrics.json (empty before the test ends).
        facts: what the command knows of the run beyond the trainer (`rotlearn-eval`: the
            checkpoint and its members), set before testing; written into
            metrics.json over the facts found, so that the file is written once.
    """

    def __init__(self, dirpath: str | Path, hparams: dict[str, Any] | None = None) -> None:
        self.dirpath = Path(dirpath)
        self.hparams = dict(hparams or {})
        self.metrics: dict[str, Any] = {}
        self.facts: dict[str, Any] = {}
        self._fit_metrics: dict[str, float] = {}
        self._fitted = False

    def on_fit_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._fit_metrics = _scalars(trainer.callback_metrics)
        self._fitted = True

    def on_test_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        metrics = {**self._fit_metrics, **_scalars(trainer.callback_metrics)}
        metrics = {k: v for k, v in metrics.items() if not k.startswith("time/")}
        for callback in trainer.callbacks:
            results = getattr(callback, "results", None)
            if callback is not self and isinstance(results, dict):
                metrics.update(_scalars(results))
        metrics.update(self._facts(trainer, pl_module), **self.facts)
        reasons = divergence(metrics, getattr(find_callback(trainer, EpochLosses), "losses", []))
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

    def _facts(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> dict[str, Any]:
        """The run's facts; those of fitting (epochs, steps, which weights, the best checkpoint's
        value) only where this trainer fitted (a test of saved weights has none of its own)."""
        config = getattr(pl_module, "run_config", None) or {}
        facts: dict[str, Any] = {
            "seed": config.get("seed"),
            "data_seed": (config.get("data") or {}).get("seed"),
            "task": getattr(pl_module, "task", None),
        }
        if self._fitted:
            facts |= {"epochs": trainer.current_epoch, "global_step": trainer.global_step,
                      "tested_weights": "best" if trainer.ckpt_path else "last",
                      "tested_epochs": pl_module.tested_epochs,
                      "tested_checkpoint": self._tested_file(trainer)}  # fmt: skip
        if facts["task"] == "rotation":
            facts["rep"] = getattr(pl_module.head, "name", None)
            facts["temperature"] = float(pl_module.belief_temperature)  # the one the test used
        checkpoints = trainer.checkpoint_callback
        if self._fitted and checkpoints and checkpoints.best_model_score is not None:
            key = f"best/{checkpoints.monitor.replace('/', '_')}"  # best/val_err_mean, ...
            facts[key] = float(checkpoints.best_model_score)
        return facts

    def _tested_file(self, trainer: pl.Trainer) -> str | None:
        """The file name, in the run's checkpoints/, of the weights the test scored (what
        `rotlearn.checkpoint.tested_checkpoint` loads for the run directory); None where they are
        not there (a checkpoint directory elsewhere)."""
        tested = Path(trainer.ckpt_path or self.dirpath / "checkpoints" / "last.ckpt")
        inside = tested.resolve().parent == (self.dirpath / "checkpoints").resolve()
        return tested.name if inside else None

    def _write(self, trainer: pl.Trainer, pl_module: pl.LightningModule, metrics: dict) -> None:
        timer = find_callback(trainer, EpochTimer)
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
        hparams = self.hparams or {"seed": metrics.get("seed")}
        headline = {k: v for k, v in metrics.items()
                    if k in HEADLINE_RESULTS or k.startswith("ood/auroc_")}  # fmt: skip
        for logger in trainer.loggers:
            if hasattr(logger, "log_results"):
                text = results_table(metrics)
                logger.log_results(hparams, headline, pl_module.tested_epochs, text)
            else:
                logger.log_hyperparams(hparams)
            logger.finalize("success")
