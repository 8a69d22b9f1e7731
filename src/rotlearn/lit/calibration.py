"""`calibrate` (default `auto`: on for every head with a belief): post-hoc calibration of the
belief on the validation set when testing starts.

`PostHocCalibration` runs when the test loop starts, after Lightning has loaded the tested weights
(`test_ckpt`: the last epoch's, or best.ckpt's). It predicts the VALIDATION set (held out from
the training side, data/README.md) with those weights and fits, in two steps:

1. one scalar temperature T on the beliefs A and the targets q by mean NLL
   (`rotlearn.bingham.fit_temperature`; A -> A / T, the mode unchanged): the belief's scale;
2. the recalibration of the tempered belief's credible levels (`rotlearn.bingham.fit_level_map`,
   Kuleshov et al. 2018): its shape, where the errors are heavier- or lighter-tailed than the
   Bingham belief, which no temperature can fix. The level-alpha region becomes the tempered
   belief's HPD region of mass `LevelMap.mass(alpha)`; the density, its mode, its NLL and the
   DT ranking are unchanged.

Then it

* sets `pl_module.belief_temperature = T` and `pl_module.belief_levels`, which the regressor
  applies in `forward` (T) and its test metrics (both): every test metric, and the OOD evaluation
  (`callbacks=ood`, which runs at the test's END and predicts through `forward`), see the
  calibrated belief, whatever the callbacks' order;
* records `calibration/temperature`, `calibration/val_nll` and `calibration/val_nll_uncalibrated`
  (nats, w.r.t. the uniform measure on SO(3)) as results of the run (metrics.json and the run's
  text table in TensorBoard; not scalar series);
* writes `<run>/checkpoints/temperature.json` beside the tested checkpoint (`TEMPERATURE_FILE`,
  read by `rotlearn.load` and `rotlearn-eval`): {"temperature", "checkpoint" (the tested file's
  name), "val_nll", "val_nll_uncalibrated" (null where not computable), "num_val",
  "credible_masses" (the level map)}.

Cost: one more pass over the validation set and `belief_samples` draws of each validation
belief (for the levels), at test start only (about a second for 1000 validation samples on a
CPU core). The fit always starts from the untempered belief (the net and head, not `forward`),
so testing twice fits the same T and map. Quaternions are scalar LAST (x, y, z, w).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch

from rotlearn.bingham import LevelMap, fit_level_map, fit_temperature, hpd_level
from rotlearn.bingham.temperature import temperature_refusal
from rotlearn.checkpoint import TEMPERATURE_FILE
from rotlearn.errors import ConfigError
from rotlearn.geometry import rotmat_to_quat
from rotlearn.io import write_json_atomic
from rotlearn.logs import progress

__all__ = ["PostHocCalibration", "validation_beliefs"]

LEVEL_SEED = 1  # the draws of the validation levels (the test metric's draws use seed 0)

log = logging.getLogger("rotlearn")


def _finish(datamodule: Any, batch: Any, module: pl.LightningModule) -> Any:
    """A loader batch as the model sees it, on its device and in its dtype (as
    `rotlearn.lit.callbacks.DataDependentInit` makes one)."""
    if hasattr(datamodule, "finish_batch"):
        return datamodule.finish_batch(batch, module.device, module.dtype)
    batch = {k: v.to(module.device) if torch.is_tensor(v) else v for k, v in batch.items()}
    return datamodule.on_after_batch_transfer(batch, 0)


def validation_beliefs(
    module: pl.LightningModule, datamodule: Any, trainer: pl.Trainer | None = None
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The untempered beliefs A (N, 4, 4) and targets q (N, 4) of the validation set, float64 on
    the CPU, predicted by `module.head(module.net(...))` in eval mode without gradients; None
    where the datamodule has no validation samples. A progress bar shows when this takes over
    2 s, unless `trainer`'s is off (`rotlearn.logs.progress`)."""
    was_training = module.training
    module.eval()
    beliefs, targets = [], []
    try:
        with torch.inference_mode():
            batches = datamodule.val_dataloader()
            for batch in progress(batches, "calibration: validation beliefs", trainer):
                batch = _finish(datamodule, batch, module)
                prediction = module.head(module.net(batch["input"]))
                beliefs.append(prediction.A.double().cpu())
                q = batch["q"] if "q" in batch else rotmat_to_quat(batch["R"])
                targets.append(q.double().cpu())
    finally:
        module.train(was_training)
    if not beliefs:
        return None
    return torch.cat(beliefs), torch.cat(targets)


class PostHocCalibration(pl.Callback):
    """Fit the belief's temperature and level map on the validation set when testing starts
    (module docstring).

    `rotlearn.cli.training.build` adds it when the config says `calibrate: true`, or `auto` (the
    default) for a head with a belief.

    Args:
        dirpath: the run directory; temperature.json is written only below it (never into
            another run's checkpoints).
        required: without validation samples, raise (`calibrate: true`) rather than test the
            belief uncalibrated with a warning (`auto`).

    Attributes:
        record: what was written to temperature.json (None before the test starts).
    """

    def __init__(self, dirpath: str | Path, required: bool = True) -> None:
        self.dirpath = Path(dirpath)
        self.required = bool(required)
        self.record: dict[str, Any] | None = None

    refusal = staticmethod(temperature_refusal)  # None: the head defines a belief

    def setup(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        why = self.refusal(getattr(pl_module, "head", None), pl_module)
        if why is not None:
            raise ConfigError("calibrate", why)

    def on_test_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        validation = validation_beliefs(pl_module, trainer.datamodule, trainer)
        if validation is None:
            if self.required:
                raise ConfigError(
                    "calibrate", "needs a validation set, but the datamodule has none"
                )
            log.warning("calibration: no validation samples; the belief is tested uncalibrated")
            return
        A, q = validation
        fit = fit_temperature(A, q)
        temperature = float(fit.temperature)
        pl_module.belief_temperature = temperature
        samples = getattr(getattr(pl_module, "test_belief", None), "num_samples", 1000)
        generator = torch.Generator().manual_seed(LEVEL_SEED)
        levels = fit_level_map(hpd_level(A / temperature, q, samples, generator))
        levels = LevelMap(levels.masses.mul(1e6).round().div(1e6))  # as temperature.json has it
        pl_module.belief_levels = levels
        if fit.at_bound is not None:
            log.warning(
                "calibration: the validation NLL still falls at the %s end of the temperature "
                "range (T = %.4g); the belief is %s",
                "sharp" if fit.at_bound == "lower" else "flat",
                temperature,
                "as sharp as supported" if fit.at_bound == "lower" else "nearly uniform",
            )
        log.info(
            "calibration: temperature %.4g on %d validation samples (mean NLL %.4f -> %.4f nats)",
            temperature, fit.num, fit.nll_before, fit.nll_after,
        )  # fmt: skip
        metrics = {"calibration/temperature": temperature, "calibration/val_nll": fit.nll_after}
        if math.isfinite(fit.nll_before):
            metrics["calibration/val_nll_uncalibrated"] = fit.nll_before
        pl_module.log_dict(metrics, on_step=False, on_epoch=True, logger=False)
        folder, name = self._tested_checkpoint(trainer)
        self.record = {
            "temperature": temperature,
            "checkpoint": name,
            "val_nll": fit.nll_after,
            "val_nll_uncalibrated": fit.nll_before if math.isfinite(fit.nll_before) else None,
            "num_val": fit.num,
            "credible_masses": levels.masses.tolist(),
        }
        if not trainer.is_global_zero:
            return
        if folder is None:
            log.info("calibration: T = %.4g, in metrics.json (no checkpoint to write %s beside)",
                     temperature, TEMPERATURE_FILE)  # fmt: skip
        elif not folder.resolve().is_relative_to(self.dirpath.resolve()):
            log.warning(
                "calibration: the tested checkpoint's directory %s is outside this run's "
                "directory %s; %s not written there",
                folder, self.dirpath, TEMPERATURE_FILE,
            )  # fmt: skip
        else:
            write_json_atomic(folder / TEMPERATURE_FILE, self.record)

    @staticmethod
    def _tested_checkpoint(trainer: pl.Trainer) -> tuple[Path | None, str]:
        """(directory, file name) of the checkpoint whose weights are tested: the one Lightning
        loaded (test_ckpt=best), else the last one (the weights in memory)."""
        if trainer.ckpt_path:
            path = Path(trainer.ckpt_path)
            return path.parent, path.name
        callback = trainer.checkpoint_callback
        last = getattr(callback, "last_model_path", "") or ""
        folder = getattr(callback, "dirpath", None)
        name = Path(last).name if last else "last.ckpt"
        return (Path(folder) if folder else None), name
