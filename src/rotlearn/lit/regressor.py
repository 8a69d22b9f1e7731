"""RotationRegressor: net + representation head + loss, with epoch-level error metrics."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import lightning.pytorch as pl
import torch
from torch import Tensor, nn
from torchmetrics import MeanMetric, SpearmanCorrCoef

from rotlearn.errors import ConfigValueError, NonFiniteError
from rotlearn.geometry import angle_deg
from rotlearn.heads import RotationHead, RotationPrediction
from rotlearn.lit.callbacks import DataDependentInit
from rotlearn.lit.state import RunStateHooks
from rotlearn.metrics import AngularError
from rotlearn.nets.autoencoder import ConvAutoEncoder
from rotlearn.trust import config_target

__all__ = ["RotationRegressor"]

OptimizerFactory = Callable[[Iterable[nn.Parameter]], torch.optim.Optimizer]
SchedulerFactory = Callable[[torch.optim.Optimizer], Any]


@config_target
class RotationRegressor(RunStateHooks, pl.LightningModule):
    """Regress rotations: `head(net(batch["input"]))`, trained with `loss(prediction, batch)`.

    Logs, once per epoch: train/loss, train/err_*, val/err_*, test/err_* (degrees; mean, median,
    p10, p90), and at test time the "predict identity" baseline test/identity_err_{mean,median}.
    Every step checks the network output and the loss for NaN/inf and stops with a
    `NonFiniteError` naming the stage, step and tensor rather than train on garbage.

    Args:
        net: backbone, (B, ...) input -> (B, head.out_dim).
        head: representation head (`rep=`).
        loss: module (prediction, batch) -> scalar.
        optimizer: partial optimizer taking the parameters (`optim=`).
        scheduler: optional partial scheduler taking the optimizer (stepped once per epoch).
    """

    task = "rotation"

    def __init__(
        self,
        net: nn.Module,
        head: RotationHead,
        loss: nn.Module,
        optimizer: OptimizerFactory,
        scheduler: SchedulerFactory | None = None,
    ) -> None:
        super().__init__()
        if isinstance(net, ConvAutoEncoder):
            raise ConfigValueError(
                "net", "the auto-encoder reconstructs images; train it with model=autoencoder"
            )
        self.net, self.head, self.loss = net, head, loss
        self.optimizer_factory, self.scheduler_factory = optimizer, scheduler
        self.train_loss = MeanMetric()
        self.train_err, self.val_err, self.test_err = AngularError(), AngularError(), AngularError()
        # the "predict identity" baseline: does the model beat the targets' own angles?
        self.test_identity_err = AngularError()
        # heads with a belief: does the DT score (paper eq. 26) rank the test errors?
        self.test_dt_spearman = SpearmanCorrCoef()
        self.run_config: dict[str, Any] | None = None  # stored in checkpoints when set
        self.test_errors: Tensor | None = None  # per-sample test errors (degrees) of the last test

    def forward(self, inputs: Tensor) -> RotationPrediction:
        return self.head(self.net(inputs))

    def configure_callbacks(self) -> list[pl.Callback]:
        """A net with a data-dependent initialisation (`initialize_from`, e.g. `PointNet`) gets
        `DataDependentInit`, whatever `callbacks=` says (it keeps that callback's timing)."""
        return [DataDependentInit()] if hasattr(self.net, "initialize_from") else []

    def _where(self, stage: str, batch_idx: int) -> str:
        return f"{stage} step {self.global_step} (epoch {self.current_epoch}, batch {batch_idx})"

    def _check_finite(self, name: str, value: Tensor, batch: dict, stage: str, idx: int) -> None:
        if bool(torch.isfinite(value).all()):
            return
        n_nan, n_inf = int(value.isnan().sum()), int(value.isinf().sum())
        shape = tuple(value.shape)
        detail = f"{n_nan} NaN and {n_inf} inf among {value.numel()} entries of shape {shape}"
        raise NonFiniteError(
            f"non-finite {name} at {self._where(stage, idx)}: {detail}; {self._cause(batch)}"
        )

    def _cause(self, batch: dict) -> str:
        """Why an output is non-finite: the batch, weights already non-finite, or an overflow
        from finite inputs and weights. Only the last two blame the training."""
        inputs = batch.get("input")
        if inputs is not None and not bool(torch.isfinite(inputs).all()):
            return "the input batch is itself non-finite (check the dataset files)"
        bad = next((n for n, p in self.named_parameters() if not bool(p.isfinite().all())), None)
        if bad is not None:
            return (
                f"the inputs are finite, but the weights are not (first: {bad}): they diverged "
                "in an earlier step (try a lower optim.lr) or were initialised from bad data"
            )
        return (
            "the inputs and the weights are finite: the computation overflowed "
            "(try a lower optim.lr)"
        )

    def _step(self, batch: dict[str, Tensor], stage: str, batch_idx: int) -> RotationPrediction:
        raw = self.net(batch["input"])
        self._check_finite("network output 'raw'", raw, batch, stage, batch_idx)
        return self.head(raw)

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        prediction = self._step(batch, "train", batch_idx)
        loss = self.loss(prediction, batch)
        self._check_finite("loss", loss, batch, "train", batch_idx)
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

    def _log_errors(self, stage: str, extra: dict[str, Tensor] | None = None) -> None:
        metric: AngularError = getattr(self, f"{stage}_err")
        values = {f"{stage}/{k}": v for k, v in metric.compute().items()}
        self.log_dict({**values, **(extra or {})}, on_step=False, on_epoch=True)
        metric.reset()

    def on_train_epoch_end(self) -> None:
        self._log_errors("train", {"train/loss": self.train_loss.compute()})
        self.train_loss.reset()

    def on_validation_epoch_end(self) -> None:
        self._log_errors("val")

    def on_test_epoch_end(self) -> None:
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
