"""AutoEncoderModule: the auto-encoder OOD baseline of the paper's Table I ("AE"), trained on the
first image of each pair; `fit_autoencoder` trains one with a Lightning Trainer."""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch
from torch import Tensor, nn
from torchmetrics import MeanMetric

from rotlearn.checkpoint import load_run
from rotlearn.errors import ConfigValueError
from rotlearn.io import atomic_write
from rotlearn.lit.finite import FINITE_CHECK_EVERY, FiniteChecks
from rotlearn.lit.state import RunStateHooks
from rotlearn.logs import logger_at_least
from rotlearn.nets.autoencoder import ConvAutoEncoder
from rotlearn.trust import config_target

__all__ = ["AutoEncoderModule", "fit_autoencoder", "load_autoencoder", "save_autoencoder"]

OptimizerFactory = Callable[[Iterable[nn.Parameter]], torch.optim.Optimizer]


@config_target
class AutoEncoderModule(FiniteChecks, RunStateHooks, pl.LightningModule):
    """Reconstruct the FIRST image of each stacked pair; its mean L1 error is the OOD score.

    Trained with the mean L1 pixel loss (paper: Adam, lr 5e-4, batch 32, 20 epochs); a pair is
    kept when its score lies below a quantile of the training scores.
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
        finite_check_every: int = FINITE_CHECK_EVERY,
    ) -> None:
        super().__init__()
        self._init_finite_checks(finite_check_every)
        if not isinstance(net, ConvAutoEncoder):
            raise ConfigValueError(
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
        images = self.net.first_image(pairs)
        return (self.net(images) - images).abs().flatten(1).mean(1)

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
    run (or a run directory's last one), read through `rotlearn.checkpoint.load_run` (weights
    only; the saved config may name allowlisted components only).

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
    module = AutoEncoderModule(run.build("net"))
    module.load_state_dict(run.state_dict)
    module.run_config = OmegaConf.to_container(run.config)
    return module.to(device).eval()


def fit_autoencoder(
    datamodule: pl.LightningDataModule,
    net_config: dict[str, Any],
    epochs: int = 20,
    lr: float = 5e-4,
    device: str | torch.device = "cpu",
    root_dir: str | os.PathLike = ".",
) -> AutoEncoderModule:
    """Train an auto-encoder on `datamodule`'s training loader with a Lightning Trainer (Adam on
    the mean L1 error, no validation, no checkpoints, no logger); returns it in eval mode.

    Args:
        datamodule: set up; its `train_dataloader` and batch hooks feed the training.
        net_config: the `rotlearn.nets.ConvAutoEncoder` config node (plain data, `_target_`);
            it is built here and kept as the module's `run_config`.
        epochs, lr: the paper's 20 epochs and 5e-4 by default.
        device: where to train (one device).
        root_dir: the Trainer's `default_root_dir`.
    """
    from hydra.utils import instantiate

    device = torch.device(device)
    module = AutoEncoderModule(
        instantiate(net_config), optimizer=functools.partial(torch.optim.Adam, lr=float(lr))
    )
    module.run_config = {"task": "autoencoder", "net": dict(net_config)}
    accelerator = {"cuda": "gpu"}.get(device.type, device.type)
    # the run's own trainer has said it: GPU available, ...
    with logger_at_least("lightning.pytorch.utilities.rank_zero"):
        trainer = _nested_trainer(accelerator, device, epochs, root_dir)
        outer = datamodule.trainer  # fit attaches the datamodule to its own trainer: give it back
        try:
            trainer.fit(module, datamodule=datamodule)
        finally:
            datamodule.trainer = outer
    return module.eval()


def _nested_trainer(
    accelerator: str, device: torch.device, epochs: int, root_dir: str | os.PathLike
) -> pl.Trainer:
    return pl.Trainer(
        accelerator=accelerator,
        devices=[device.index or 0] if device.type == "cuda" else 1,
        max_epochs=int(epochs),
        limit_val_batches=0,
        num_sanity_val_steps=0,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        default_root_dir=str(Path(root_dir)),
    )


def save_autoencoder(module: AutoEncoderModule, path: str | os.PathLike) -> Path:
    """Write `module`'s weights and `run_config` as a checkpoint that `load_autoencoder` reads
    (tensors and plain data only), atomically; returns the path."""
    path = Path(path)
    with atomic_write(path) as tmp:
        torch.save({"state_dict": module.state_dict(), "rotlearn_config": module.run_config}, tmp)
    return path
