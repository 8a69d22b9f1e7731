"""AutoEncoderModule: the auto-encoder OOD baseline of the paper's Table I ("AE"), trained on the
first image of each pair as its own run (`model=autoencoder`, `experiment=<data>_autoencoder`);
the OOD evaluation reads its checkpoint (`callbacks.ood.autoencoder_ckpt`)."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Annotated, Any

import lightning.pytorch as pl
import torch
from torch import Tensor, nn
from torchmetrics import MeanMetric

from rotlearn.checkpoint import load_run
from rotlearn.errors import ConfigError
from rotlearn.lit.finite import FINITE_CHECK_EVERY, FiniteChecks
from rotlearn.lit.state import RunStateHooks
from rotlearn.nets.autoencoder import ConvAutoEncoder, load_autoencoder_net
from rotlearn.trust import config_target

if TYPE_CHECKING:  # constraints of the config values, checked by rotlearn.config
    from annotated_types import Gt

__all__ = ["AutoEncoderModule", "load_autoencoder"]

OptimizerFactory = Callable[[Iterable[nn.Parameter]], torch.optim.Optimizer]


@config_target
class AutoEncoderModule(FiniteChecks, RunStateHooks, pl.LightningModule):
    """Reconstruct the FIRST image of each stacked pair; its mean L1 error is the OOD score.

    Trained with the mean L1 pixel loss (paper: Adam, lr 5e-4, batch 32, 20 epochs); a pair is
    kept when its score lies below a quantile of the reference scores (`rotlearn.ood`: the
    validation pairs' by default, the training pairs' in the paper).
    Logs, once per epoch: train/loss, val/loss (mean L1 over the epoch's pixels) and, at test,
    test/recon_mean (the mean score of the test pairs).

    Args:
        net: the auto-encoder, (B, C, S, S) -> (B, C, S, S).
        optimizer: partial optimizer taking the parameters (`optim=`); None for inference only.
        finite_check_every: training steps between two reads of the NaN/inf check of the
            reconstruction errors (`rotlearn.lit.finite`; 1 reads every step).
    """

    task = "autoencoder"

    def __init__(
        self,
        net: ConvAutoEncoder,
        optimizer: OptimizerFactory | None = None,
        finite_check_every: Annotated[int, Gt(0)] = FINITE_CHECK_EVERY,
    ) -> None:
        super().__init__()
        self._init_finite_checks(finite_check_every)
        if not isinstance(net, ConvAutoEncoder):
            raise ConfigError(
                "net", f"model=autoencoder trains net=autoencoder, not {type(net).__name__}"
            )
        self.net = net
        self.optimizer_factory = optimizer
        # NaN is the finite check's to report (MeanMetric's own check syncs with the device)
        self.train_loss, self.val_loss, self.test_score = (
            MeanMetric(nan_strategy="disable") for _ in range(3)
        )
        self.run_config: dict[str, Any] | None = None  # stored in checkpoints when set

    def forward(self, images: Tensor) -> Tensor:
        """(B, C, S, S) images -> (B, C, S, S) reconstructions."""
        return self.net(images)

    def errors(self, pairs: Tensor) -> Tensor:
        """(B, 2C, S, S) stacked pairs -> (B,) mean absolute reconstruction error of the first
        image of each pair (differentiable; the second image is never looked at)."""
        return self.net.reconstruction_error(pairs)

    @torch.no_grad()
    def score(self, pairs: Tensor) -> Tensor:
        """OOD score of (B, 2C, S, S) stacked pairs: (B,) per-sample mean L1 reconstruction error
        of the first image, >= 0; lower = more in-distribution. Call in eval mode (BatchNorm)."""
        return self.errors(pairs.to(self.device, self.dtype))

    def _loss(self, batch: dict[str, Tensor], stage: str, batch_idx: int) -> Tensor:
        errors = self.errors(batch["input"])
        self._observe("reconstruction error", errors, stage, batch_idx, self._inputs_bad(batch))
        return errors

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        loss = self._loss(batch, "train", batch_idx).mean()
        self.train_loss.update(loss.detach())
        return loss

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self.val_loss.update(self._loss(batch, "val", batch_idx))

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self.test_score.update(self._loss(batch, "test", batch_idx))

    def _log_mean(self, name: str, metric: MeanMetric) -> None:
        """The metric's mean: a per-epoch series for train and val, one result for test."""
        logger = False if name.startswith("test/") else None  # None: to the loggers
        self.log(name, metric.compute(), on_step=False, on_epoch=True, logger=logger)
        metric.reset()

    def on_train_epoch_end(self) -> None:
        self._read_finite()
        self._log_mean("train/loss", self.train_loss)

    def on_validation_epoch_end(self) -> None:
        self._read_finite()
        self._log_mean("val/loss", self.val_loss)

    def on_test_epoch_end(self) -> None:
        self._read_finite()
        self._log_mean("test/recon_mean", self.test_score)

    def configure_optimizers(self) -> torch.optim.Optimizer:
        if self.optimizer_factory is None:
            raise ValueError("AutoEncoderModule was built without an optimizer; it cannot train")
        return self.optimizer_factory(self.parameters())


def load_autoencoder(
    ckpt_path: str | os.PathLike, device: str | torch.device = "cpu"
) -> AutoEncoderModule:
    """An `AutoEncoderModule`, in eval mode on `device`, from a checkpoint of a `model=autoencoder`
    run (or a run directory: the weights its test scored), read through
    `rotlearn.checkpoint.load_run` (weights only; the saved config may name allowlisted components
    only).

    Raises:
        FileNotFoundError: no such checkpoint.
        UnsafeCheckpointError, UntrustedConfigError: see `load_run`.
        ValueError: the checkpoint is not from an auto-encoder run (the message names the path).
    """
    from omegaconf import OmegaConf

    run = load_run(ckpt_path)
    if run.task != "autoencoder":
        raise ValueError(
            f"{run.path} is not an auto-encoder checkpoint: its run has task={run.task!r} "
            "(train one with model=autoencoder, e.g. experiment=kitti_autoencoder)"
        )
    module = AutoEncoderModule(load_autoencoder_net(run.path))
    module.run_config = OmegaConf.to_container(run.config)
    return module.to(device).eval()
