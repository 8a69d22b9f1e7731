"""RotationRegressor: net + representation head + loss, with epoch-level error metrics."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Annotated, Any

import lightning.pytorch as pl
import torch
from torch import Tensor, nn
from torchmetrics import MeanMetric

from rotlearn.bingham import LevelMap
from rotlearn.errors import ConfigError
from rotlearn.geometry import angle_deg, rotmat_to_quat
from rotlearn.heads import RotationHead, RotationPrediction
from rotlearn.lit.callbacks import DataDependentInit
from rotlearn.lit.finite import FINITE_CHECK_EVERY, FiniteChecks
from rotlearn.lit.state import RunStateHooks
from rotlearn.metrics import AngularError, BeliefCalibration, SampleValues
from rotlearn.nets.autoencoder import ConvAutoEncoder
from rotlearn.scores import SCORES, auroc, spearman
from rotlearn.trust import config_target

if TYPE_CHECKING:  # constraints of the config values, checked by rotlearn.config
    from annotated_types import Gt, MinLen

__all__ = ["NOISIEST_FRACTION", "RotationRegressor", "compile_modules", "noisiest"]

OptimizerFactory = Callable[[Iterable[nn.Parameter]], torch.optim.Optimizer]
SchedulerFactory = Callable[[torch.optim.Optimizer], Any]
NOISIEST_FRACTION = 0.1  # test/<score>_auroc_noisiest: the top decile of difficulty


def noisiest(difficulty: Tensor, fraction: float = NOISIEST_FRACTION) -> Tensor:
    """(N,) bool: the samples whose difficulty reaches its (1 - fraction)-quantile (linear
    interpolation), i.e. the top `fraction` of difficulty; samples tied at the threshold are
    all in (all of them where the difficulty is constant)."""
    return difficulty >= torch.quantile(difficulty.double(), 1.0 - fraction)


def compile_modules(compile: bool | str, *modules: nn.Module) -> None:
    """Compile each module's forward in place with `torch.compile` (`nn.Module.compile`: the
    parameters and state_dict keys stay those of the eager module). `compile`: False does
    nothing, True uses torch.compile's default backend, a string names the backend."""
    if compile is False:
        return
    options = {} if compile is True else {"backend": compile}
    for module in modules:
        module.compile(**options)


@config_target
class RotationRegressor(FiniteChecks, RunStateHooks, pl.LightningModule):
    """Regress rotations: `head(net(batch["input"]))`, trained with `loss(prediction, batch)`.

    Logs, once per epoch, to the loggers: train/loss, val/loss, train/lr, train/err_* and val/err_*
    (degrees; mean, median, p10, p90). Everything measured at test time is one result per run:
    kept in `trainer.callback_metrics` (and so in metrics.json, `rotlearn.lit.RunRecords`), never
    logged as a scalar series; the records pick the headline ones for TensorBoard. They are
    test/err_* and the "predict identity" baseline test/identity_err_{mean,median}.
    At test time also, for every OOD score the head gives (`rotlearn.scores.SCORES`: raw_norm
    for every head, dt and eigengap with a belief): test/<score>_spearman, its Spearman rank
    correlation with the error (positive for dt, whose low values are confident; negative for
    the keep-above eigengap and raw_norm where they work), and, where the test batches carry a
    per-sample "difficulty" (B,) (growing with the expected error, e.g. the noise level),
    test/<score>_auroc_noisiest: the AUROC of the score at flagging the noisiest tenth of the
    samples (`noisiest`; 1 perfect, 0.5 chance). Heads with a belief (`prediction.A`) also log
    its calibration (`rotlearn.metrics.BeliefCalibration`): test/nll (mean negative
    log-likelihood of the targets in nats, w.r.t. the uniform probability measure on SO(3)),
    test/ece and test/coverage_<alpha> (alpha = 0.1 ... 0.9: the fraction of targets inside the
    highest-density credible region of mass alpha), and, in a `TensorBoardRunLogger`, the
    reliability diagram `test/reliability` (coverage against alpha). The belief is the one used,
    `belief_temperature` applied; where that is not 1, test/temperature and the same numbers of
    the untempered belief, test/uncalibrated_nll, test/uncalibrated_ece and
    test/uncalibrated_coverage_<alpha>, are logged too.
    Every step's network output and loss are checked for NaN/inf on the device and the check is
    read every `finite_check_every` training steps and at every loop's end
    (`rotlearn.lit.finite`): a failure stops the run with a `NonFiniteError` naming the stage,
    step and tensor that failed first, and no update is applied after it.

    Args:
        net: backbone, (B, ...) input -> (B, head.out_dim).
        head: representation head (`rep=`).
        loss: module (prediction, batch) -> scalar.
        optimizer: partial optimizer taking the parameters (`optim=`).
        scheduler: optional partial scheduler taking the optimizer (stepped once per epoch).
        finite_check_every: training steps between two reads of the NaN/inf check (a host sync
            each; 1 reads every step).
        compile: compile the net and the head with `torch.compile` (in place: `nn.Module.compile`,
            so checkpoints keep their keys): True for its default backend (inductor), or a
            backend's name (e.g. "aot_eager", which needs no C++ compiler); False: eager.
        belief_samples: draws of each test belief for its credible levels (the coverage's Monte
            Carlo error per level is <= 1 / (2 sqrt(belief_samples)) per sample).

    Attributes:
        belief_temperature: the belief's temperature T (A -> A / T, `RotationPrediction.
            with_temperature`), applied by `forward` and every step; 1 (untempered) until a
            post-hoc calibration sets it after fitting. A plain float: neither a parameter nor a
            buffer.
        belief_levels: the recalibration of the tempered belief's credible levels
            (`rotlearn.bingham.LevelMap`), set by the post-hoc calibration; None: the belief's
            own HPD levels. It changes only which HPD region is called the level-alpha region.
    """

    task = "rotation"

    def __init__(
        self,
        net: nn.Module,
        head: RotationHead,
        loss: nn.Module,
        optimizer: OptimizerFactory,
        scheduler: SchedulerFactory | None = None,
        finite_check_every: Annotated[int, Gt(0)] = FINITE_CHECK_EVERY,
        compile: bool | Annotated[str, MinLen(1)] = False,
        belief_samples: Annotated[int, Gt(0)] = 1000,
    ) -> None:
        super().__init__()
        self._init_finite_checks(finite_check_every)
        if isinstance(net, ConvAutoEncoder):
            raise ConfigError(
                "net", "the auto-encoder reconstructs images; train it with model=autoencoder"
            )
        self.net, self.head, self.loss = net, head, loss
        compile_modules(compile, self.net, self.head)
        self.optimizer_factory, self.scheduler_factory = optimizer, scheduler
        # NaN is the finite check's to report (MeanMetric's own check syncs with the device)
        self.train_loss = MeanMetric(nan_strategy="disable")
        self.val_loss = MeanMetric(nan_strategy="disable")
        self.train_err, self.val_err, self.test_err = AngularError(), AngularError(), AngularError()
        # the "predict identity" baseline: does the model beat the targets' own angles?
        self.test_identity_err = AngularError()
        # do the OOD scores (DT: paper eq. 26) rank the test errors and flag the noisiest samples?
        # Those registered now that a prediction gives (the auto-encoder's needs its own model).
        self._scores = {name: s for name, s in SCORES.items() if s.fn is not None}
        self.test_samples = SampleValues(("error", "difficulty", *self._scores))
        # heads with a belief: is it calibrated (as used, and untempered when tempered)?
        self.test_belief = BeliefCalibration(belief_samples)
        self.test_untempered_belief = BeliefCalibration(belief_samples)
        self.belief_temperature: float = 1.0
        self.belief_levels: LevelMap | None = None
        self.run_config: dict[str, Any] | None = None  # stored in checkpoints when set
        self.test_errors: Tensor | None = None  # per-sample test errors (degrees) of the last test

    def forward(self, inputs: Tensor) -> RotationPrediction:
        return self.head(self.net(inputs)).with_temperature(self.belief_temperature)

    def configure_callbacks(self) -> list[pl.Callback]:
        """A net with a data-dependent initialisation (`initialize_from`, e.g. `PointNet`) gets
        `DataDependentInit`, whatever `callbacks=` says (it keeps that callback's timing); once
        (testing after fitting finds it there already)."""
        if not hasattr(self.net, "initialize_from"):
            return []
        if any(isinstance(cb, DataDependentInit) for cb in self.trainer.callbacks):
            return []
        return [DataDependentInit()]

    def _step(self, batch: dict[str, Tensor], stage: str, batch_idx: int) -> RotationPrediction:
        prediction, _ = self._observed_step(batch, stage, batch_idx)
        return prediction

    def _observed_step(
        self, batch: dict[str, Tensor], stage: str, batch_idx: int
    ) -> tuple[RotationPrediction, Tensor | None]:
        """The head's prediction from the network output, which the finite check observes; also
        whether the input batch is non-finite (a device flag for the loss's observation).

        The check is read later, so a non-finite output must not stop the step here: it reaches
        the head as zeros (a solver such as `eigh` raises on NaN), the failure already recorded
        and the update to come zeroed. The belief is tempered by `belief_temperature`."""
        prediction, inputs_bad = self._untempered_step(batch, stage, batch_idx)
        return prediction.with_temperature(self.belief_temperature), inputs_bad

    def _untempered_step(
        self, batch: dict[str, Tensor], stage: str, batch_idx: int
    ) -> tuple[RotationPrediction, Tensor | None]:
        """`_observed_step` before the temperature is applied."""
        inputs_bad = self._inputs_bad(batch)
        raw = self.net(batch["input"])
        self._observe("network output 'raw'", raw, stage, batch_idx, inputs_bad)
        raw = torch.nan_to_num(raw, nan=0.0, posinf=0.0, neginf=0.0)
        return self.head(raw), inputs_bad

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        prediction, inputs_bad = self._observed_step(batch, "train", batch_idx)
        loss = self.loss(prediction, batch)
        self._observe("loss", loss, "train", batch_idx, inputs_bad)
        self.train_loss.update(loss.detach())
        self.train_err.update(prediction.R.detach(), batch["R"])
        return loss

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        prediction = self._step(batch, "val", batch_idx)
        self.val_err.update(prediction.R, batch["R"])
        self.val_loss.update(self.loss(prediction, batch))

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        untempered, _ = self._untempered_step(batch, "test", batch_idx)
        prediction = untempered.with_temperature(self.belief_temperature)
        self.test_err.update(prediction.R, batch["R"])
        identity = torch.eye(3, dtype=batch["R"].dtype, device=batch["R"].device)
        self.test_identity_err.update(identity.expand_as(batch["R"]), batch["R"])
        has_eigenvalues = prediction.eigenvalues is not None
        has_members = prediction.members is not None
        values = {name: score.fn(prediction) for name, score in self._scores.items()
                  if (has_eigenvalues or not score.needs_eigenvalues)
                  and (has_members or not score.needs_members)}  # fmt: skip
        values["error"] = angle_deg(prediction.R, batch["R"])
        if "difficulty" in batch:
            values["difficulty"] = batch["difficulty"]
        self.test_samples.update(**values)
        if prediction.A is not None:
            q = batch["q"] if "q" in batch else rotmat_to_quat(batch["R"])
            self.test_belief.update(prediction.A, q)
            if self.belief_temperature != 1:
                self.test_untempered_belief.update(untempered.A, q)

    def predict_step(self, batch: dict[str, Tensor], batch_idx: int) -> RotationPrediction:
        return self._step(batch, "predict", batch_idx).detach()

    def on_predict_epoch_end(self) -> None:
        self._read_finite()

    def _log_errors(self, stage: str, extra: dict[str, Any] | None = None) -> None:
        """The stage's error percentiles (and `extra`); per-epoch series for train and val, one
        result (no logger) for test."""
        metric: AngularError = getattr(self, f"{stage}_err")
        values = {f"{stage}/{k}": v for k, v in metric.compute().items()}
        logger = False if stage == "test" else None  # None: Lightning's default, to the loggers
        self.log_dict({**values, **(extra or {})}, on_step=False, on_epoch=True, logger=logger)
        metric.reset()

    def on_train_epoch_end(self) -> None:
        self._read_finite()
        lr = self.trainer.optimizers[0].param_groups[0]["lr"] if self.trainer.optimizers else None
        extra = {"train/loss": self.train_loss.compute()}
        if lr is not None:
            extra["train/lr"] = float(lr)
        self._log_errors("train", extra)
        self.train_loss.reset()

    def on_validation_epoch_end(self) -> None:
        self._read_finite()
        self._log_errors("val", {"val/loss": self.val_loss.compute()})
        self.val_loss.reset()

    def on_test_epoch_end(self) -> None:
        self._read_finite()
        self.test_errors = self.test_err.values().cpu()
        self._log_errors("test")
        baseline = self.test_identity_err.compute()
        self.log_dict(
            {f"test/identity_{k}": baseline[k] for k in ("err_mean", "err_median")},
            on_step=False,
            on_epoch=True,
            logger=False,
        )
        self.test_identity_err.reset()
        self._log_scores()
        self._log_beliefs()

    def _log_scores(self) -> None:
        """test/<score>_spearman and test/<score>_auroc_noisiest (class docstring)."""
        if not self.test_samples.update_count:
            return
        samples = self.test_samples.compute()
        self.test_samples.reset()
        errors, difficulty = samples.pop("error"), samples.pop("difficulty", None)
        if difficulty is not None and len(difficulty) != len(errors):
            difficulty = None  # only some test batches carried one: no decile to rank
        flagged = noisiest(difficulty) if difficulty is not None else None
        logged = {}
        for name, scores in samples.items():
            logged[f"test/{name}_spearman"] = spearman(scores, errors)
            if flagged is not None:
                keep_below = self._scores[name].keep_below
                logged[f"test/{name}_auroc_noisiest"] = auroc(scores, flagged, keep_below)
        self.log_dict(logged, on_step=False, on_epoch=True, logger=False)

    def _log_beliefs(self) -> None:
        """test/nll, test/ece, test/coverage_<alpha> of the belief as used, the untempered
        belief's where it differs, the tempered belief's own levels where a level map
        recalibrates them, and the reliability diagram (class docstring)."""
        if not self.test_belief.update_count:
            return
        self.test_belief.level_map = self.belief_levels
        belief = self.test_belief.compute()
        curves = {"belief": {k: v for k, v in belief.items() if not k.startswith("unmapped_")}}
        if self.belief_levels is not None:
            curves["tempered"] = {k.removeprefix("unmapped_"): v for k, v in belief.items()
                                  if k.startswith("unmapped_")}  # fmt: skip
        if self.test_untempered_belief.update_count:
            curves["uncalibrated"] = self.test_untempered_belief.compute()
        logged = {f"test/{k}": v for k, v in curves["belief"].items()}
        if "tempered" in curves:
            logged.update({f"test/tempered_{k}": v for k, v in curves["tempered"].items()})
        if "uncalibrated" in curves:
            logged.update({f"test/uncalibrated_{k}": v for k, v in curves["uncalibrated"].items()})
        if self.belief_temperature != 1 or self.belief_levels is not None:
            logged["test/temperature"] = float(self.belief_temperature)
        self.log_dict(logged, on_step=False, on_epoch=True, logger=False)
        for metric in (self.test_belief, self.test_untempered_belief):
            metric.reset()
        self._reliability_figure(curves)

    def _reliability_figure(self, curves: dict[str, dict[str, Tensor]]) -> None:
        """The reliability diagram, naming the remedy of an uncalibrated belief, in each logger
        that draws figures (`TensorBoardRunLogger`; global rank 0)."""
        loggers = [lg for lg in self.loggers if hasattr(lg, "log_figure")]
        if not loggers or not self.trainer.is_global_zero:
            return
        from rotlearn.report.figures import calibration_remedy, reliability_figure

        temperature, alphas = float(self.belief_temperature), self.test_belief.alphas
        tempered = f"T = {temperature:.3g}" if temperature != 1 else "belief"
        labels = {
            "belief": f"{tempered} + level map" if self.belief_levels is not None else tempered,
            "tempered": f"{tempered} (its own levels)",
            "uncalibrated": "untempered (T = 1)",
        }
        ece = float(curves["belief"]["ece"])
        calibrated = temperature != 1 or self.belief_levels is not None
        remedy = calibration_remedy(
            ece, calibrated, getattr(self.loss, "parameter", None) is not None,
            getattr(self.head, "name", None),
        )  # fmt: skip
        figure = reliability_figure(
            [
                {
                    "label": labels[name],
                    "alphas": alphas,
                    "coverage": [float(metrics[f"coverage_{a:g}"]) for a in alphas],
                    "ece": float(metrics["ece"]),
                    "dashed": name != "belief",
                }
                for name, metrics in curves.items()
            ],
            remedy=remedy,
        )
        for logger in loggers:
            logger.log_figure("test/reliability", figure, self.tested_epochs)

    def configure_optimizers(self) -> Any:
        optimizer = self.optimizer_factory(self.parameters())
        if self.scheduler_factory is None:
            return optimizer
        scheduler = self.scheduler_factory(optimizer)
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": "epoch"},
        }
