"""RotationRegressor: net + representation head + loss, with epoch-level error metrics."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterable
from typing import Any

import lightning.pytorch as pl
import torch
from torch import Tensor, nn
from torchmetrics import MeanMetric, SpearmanCorrCoef

from rotlearn.errors import ConfigValueError
from rotlearn.geometry import angle_deg
from rotlearn.heads import RotationHead, RotationPrediction
from rotlearn.lit.callbacks import DataDependentInit
from rotlearn.lit.finite import FINITE_CHECK_EVERY, FiniteChecks
from rotlearn.lit.state import RunStateHooks
from rotlearn.metrics import AngularError
from rotlearn.nets.autoencoder import ConvAutoEncoder
from rotlearn.trust import config_target

__all__ = ["RotationRegressor", "compile_modules"]

OptimizerFactory = Callable[[Iterable[nn.Parameter]], torch.optim.Optimizer]
SchedulerFactory = Callable[[torch.optim.Optimizer], Any]


def compile_modules(compile: bool | str, *modules: nn.Module) -> None:
    """Compile each module's forward in place with `torch.compile` (`nn.Module.compile`: the
    parameters and state_dict keys stay those of the eager module). `compile`: False does
    nothing, True uses torch.compile's default backend, a string names the backend."""
    if isinstance(compile, str) and not compile:
        raise ConfigValueError("compile", "must be true, false or a torch.compile backend's name")
    if compile is False:
        return
    options = {} if compile is True else {"backend": compile}
    for module in modules:
        module.compile(**options)


@config_target
class RotationRegressor(FiniteChecks, RunStateHooks, pl.LightningModule):
    """Regress rotations: `head(net(batch["input"]))`, trained with `loss(prediction, batch)`.

    Logs, once per epoch: train/loss, train/err_*, val/err_*, test/err_* (degrees; mean, median,
    p10, p90), and at test time the "predict identity" baseline test/identity_err_{mean,median}.
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
    """

    task = "rotation"

    def __init__(
        self,
        net: nn.Module,
        head: RotationHead,
        loss: nn.Module,
        optimizer: OptimizerFactory,
        scheduler: SchedulerFactory | None = None,
        finite_check_every: int = FINITE_CHECK_EVERY,
        compile: bool | str = False,
    ) -> None:
        super().__init__()
        self._init_finite_checks(finite_check_every)
        if isinstance(net, ConvAutoEncoder):
            raise ConfigValueError(
                "net", "the auto-encoder reconstructs images; train it with model=autoencoder"
            )
        self.net, self.head, self.loss = net, head, loss
        compile_modules(compile, self.net, self.head)
        self.optimizer_factory, self.scheduler_factory = optimizer, scheduler
        # NaN is the finite check's to report (MeanMetric's own check syncs with the device)
        self.train_loss = MeanMetric(nan_strategy="disable")
        self.train_err, self.val_err, self.test_err = AngularError(), AngularError(), AngularError()
        # the "predict identity" baseline: does the model beat the targets' own angles?
        self.test_identity_err = AngularError()
        # heads with a belief: does the DT score (paper eq. 26) rank the test errors?
        with warnings.catch_warnings():  # it keeps every test sample: so does test_err
            warnings.filterwarnings("ignore", message=r"Metric `SpearmanCorrcoef` will save all")
            self.test_dt_spearman = SpearmanCorrCoef()
        self.run_config: dict[str, Any] | None = None  # stored in checkpoints when set
        self.test_errors: Tensor | None = None  # per-sample test errors (degrees) of the last test

    def forward(self, inputs: Tensor) -> RotationPrediction:
        return self.head(self.net(inputs))

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
        and the update to come zeroed."""
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
        self.val_err.update(self._step(batch, "val", batch_idx).R, batch["R"])

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        prediction = self._step(batch, "test", batch_idx)
        self.test_err.update(prediction.R, batch["R"])
        identity = torch.eye(3, dtype=batch["R"].dtype, device=batch["R"].device)
        self.test_identity_err.update(identity.expand_as(batch["R"]), batch["R"])
        if prediction.dt is not None:
            dt = prediction.dt
            errors = angle_deg(prediction.R, batch["R"])
            self.test_dt_spearman.update(dt.flatten().double(), errors.flatten().double())

    def predict_step(self, batch: dict[str, Tensor], batch_idx: int) -> RotationPrediction:
        return self._step(batch, "predict", batch_idx).detach()

    def on_predict_epoch_end(self) -> None:
        self._read_finite()

    def _log_errors(self, stage: str, extra: dict[str, Tensor] | None = None) -> None:
        metric: AngularError = getattr(self, f"{stage}_err")
        values = {f"{stage}/{k}": v for k, v in metric.compute().items()}
        self.log_dict({**values, **(extra or {})}, on_step=False, on_epoch=True)
        metric.reset()

    def on_train_epoch_end(self) -> None:
        self._read_finite()
        self._log_errors("train", {"train/loss": self.train_loss.compute()})
        self.train_loss.reset()

    def on_validation_epoch_end(self) -> None:
        self._read_finite()
        self._log_errors("val")

    def on_test_epoch_end(self) -> None:
        self._read_finite()
        self.test_errors = self.test_err.values().cpu()
        self._log_errors("test")
        baseline = self.test_identity_err.compute()
        self.log_dict(
            {f"test/identity_{k}": baseline[k] for k in ("err_mean", "err_median")},
            on_step=False,
            on_epoch=True,
        )
        self.test_identity_err.reset()
        if self.test_dt_spearman.update_count:
            rho = self.test_dt_spearman.compute()
            self.log("test/dt_spearman", rho, on_step=False, on_epoch=True)
            self.test_dt_spearman.reset()

    def configure_optimizers(self) -> Any:
        optimizer = self.optimizer_factory(self.parameters())
        if self.scheduler_factory is None:
            return optimizer
        scheduler = self.scheduler_factory(optimizer)
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": "epoch"},
        }
