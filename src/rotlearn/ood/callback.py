"""`callbacks=ood`: OOD evaluation at test time (paper section V-A, Table I, Fig. 6-8).

A thin callback: after the regular test, it reads the datamodule through `OODDataSource`, scores
the TRAINING set (unshuffled, unaugmented), the clean test set and the same test set with its last
`corrupt_fraction` randomly erased, and pure-noise pairs (`rotlearn.ood.evaluation`), then writes
`ood.csv` and a Table I-style `ood.md` to the run directory, the calibrated DT threshold beside the
run's checkpoints (`ood_thresholds.json`, read by `rotlearn.load` for keep flags), and scalars and
figures to TensorBoard (`rotlearn.ood.report`).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import numpy as np
import torch
from lightning.pytorch.loggers import TensorBoardLogger
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from rotlearn.data.corruption import corrupted_flags
from rotlearn.errors import ConfigValueError
from rotlearn.ood.evaluation import (
    calibrated_threshold,
    rejection_table,
    score_sets,
)
from rotlearn.ood.scores import SCORES, available_scores
from rotlearn.ood.source import OODDataSource
from rotlearn.trust import config_target

__all__ = ["OODEvaluation"]

log = logging.getLogger("rotlearn")


@config_target
class OODEvaluation(pl.Callback):
    """Score, threshold and evaluate OOD rejection when the test loop ends (module docstring).

    Args:
        quantiles: fractions of the training scores kept, each in [0, 1] (paper: 0.75 KITTI,
            0.5 MAV, 1.0 for the auto-encoder).
        scores: among dt, eigengap, raw_norm, autoencoder; those the head cannot give (dt and
            eigengap need the A head) or that lack a checkpoint (autoencoder) are skipped.
        autoencoder_ckpt: checkpoint of `rotlearn-train experiment=<data>_autoencoder`.
        autoencoder_train: without a checkpoint, train an auto-encoder here first (a Lightning
            Trainer, `rotlearn.lit.autoencoder.fit_autoencoder`), on the same training pairs:
            {epochs, lr, and ConvAutoEncoder's channels, hidden, latent}; it is saved as
            `<run>/autoencoder.ckpt` (reusable as `autoencoder_ckpt`). For demos; on real data
            train it once with its experiment instead.
        corrupt_fraction: the last fraction of the test set that is erased for the corrupted set.
        table: score -> quantile shown in `ood.md`'s Table I (others: the largest quantile <= 0.75);
            these quantiles are evaluated too.
        noise_pairs: pure-noise input pairs scored for the box plots.
        max_train_pairs: score at most this many training pairs (evenly spaced); null: all.
        unseen_scenes_ood: count test pairs from sequences / scenes absent from training as OOD
            (with the erased ones) in precision, recall and AUROC: the MAV experiment, where
            the indoor and transition scenes are the unseen environments (paper Fig. 8).
    """

    def __init__(
        self,
        quantiles: list[float] = (0.25, 0.5, 0.75, 1.0),
        scores: list[str] = ("dt", "eigengap", "raw_norm", "autoencoder"),
        autoencoder_ckpt: str | None = None,
        autoencoder_train: dict[str, Any] | None = None,
        corrupt_fraction: float = 0.5,
        table: dict[str, float] | None = None,
        noise_pairs: int = 64,
        max_train_pairs: int | None = None,
        unseen_scenes_ood: bool = False,
    ) -> None:
        super().__init__()
        self.quantiles = [float(q) for q in quantiles]
        bad = [q for q in self.quantiles if not 0.0 <= q <= 1.0 or math.isnan(q)]
        if bad or not self.quantiles:
            raise ConfigValueError("quantiles", f"each must lie in [0, 1], got {list(quantiles)}")
        unknown = sorted(set(scores) - set(SCORES))
        if unknown:
            raise ConfigValueError("scores", f"unknown {unknown}; choose from {sorted(SCORES)}")
        if autoencoder_ckpt and not Path(autoencoder_ckpt).exists():
            raise ConfigValueError("autoencoder_ckpt", f"{autoencoder_ckpt} does not exist")
        if not 0.0 < corrupt_fraction <= 1.0:
            raise ConfigValueError(
                "corrupt_fraction", f"must lie in (0, 1], got {corrupt_fraction}"
            )
        self.score_names = list(scores)
        self.autoencoder_ckpt = autoencoder_ckpt
        if isinstance(autoencoder_train, DictConfig):  # plain data: it goes into a checkpoint
            autoencoder_train = OmegaConf.to_container(autoencoder_train, resolve=True)
        self.autoencoder_train = dict(autoencoder_train or {})
        self.corrupt_fraction = float(corrupt_fraction)
        self.table = {"autoencoder": 1.0, **(table or {})}
        self.noise_pairs, self.max_train_pairs = int(noise_pairs), max_train_pairs
        self.unseen_scenes_ood = bool(unseen_scenes_ood)

    def _autoencoder(self, trainer: pl.Trainer, device: torch.device):
        """The auto-encoder of the `autoencoder` score: loaded, trained here on the datamodule's
        training pairs, or None."""
        from rotlearn.lit.autoencoder import fit_autoencoder, load_autoencoder, save_autoencoder

        if "autoencoder" not in self.score_names:
            return None
        if self.autoencoder_ckpt:
            return load_autoencoder(self.autoencoder_ckpt, device=device)
        if not self.autoencoder_train:
            return None
        source: OODDataSource = trainer.datamodule
        spec = dict(self.autoencoder_train)
        epochs, lr = int(spec.pop("epochs", 20)), float(spec.pop("lr", 5e-4))
        channels, size = source.pair_shape()[0], source.pair_shape()[-1]
        net = {"_target_": "rotlearn.nets.ConvAutoEncoder", "pair_channels": channels,
               "image_size": size, **spec}  # fmt: skip
        log.info("OOD evaluation: training an auto-encoder for %d epochs", epochs)
        run_dir = Path(trainer.default_root_dir)
        # the test loop runs in inference mode; training needs autograd
        with torch.inference_mode(False), torch.enable_grad():
            module = fit_autoencoder(source, net, epochs, lr, device, run_dir)
        path = save_autoencoder(module, run_dir / "autoencoder.ckpt")
        return load_autoencoder(path, device=device)

    def _loaders(
        self, source: OODDataSource, device: torch.device, dtype: torch.dtype
    ) -> tuple[dict[str, Iterable[dict[str, Tensor]]], dict[str, Tensor]]:
        """Finished batches of the train, clean, corrupted and noise sets, and the OOD flags of
        the test sets (erased pairs, and pairs from unseen scenes when `unseen_scenes_ood`)."""
        n_train, n_test = source.pair_count("train"), source.pair_count("test")
        keep = None
        if self.max_train_pairs and n_train > self.max_train_pairs:
            keep = np.linspace(0, n_train - 1, self.max_train_pairs).astype(int).tolist()
        erase = corrupted_flags(n_test, self.corrupt_fraction)
        unseen = source.unseen_pairs("test") & self.unseen_scenes_ood
        finish = functools.partial(source.finish_batch, device=device, dtype=dtype)
        loaders = {
            "train": map(finish, source.eval_loader("train", indices=keep)),
            "clean": map(finish, source.eval_loader("test", erase=torch.zeros_like(erase))),
            "corrupted": map(finish, source.eval_loader("test", erase=erase)),
            "noise": [finish(source.noise_batch(self.noise_pairs))],
        }
        return loaders, {"clean": unseen, "corrupted": erase | unseen}

    def on_test_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        source = trainer.datamodule
        if not isinstance(source, OODDataSource):
            raise ConfigValueError(
                "callbacks.ood", "needs an image-pair datamodule (data=kitti or data=mav)"
            )
        if not trainer.is_global_zero:
            return
        autoencoder = self._autoencoder(trainer, pl_module.device)
        scores = available_scores(
            self.score_names, pl_module.head.defines_belief, autoencoder is not None
        )
        input_scores = {"autoencoder": autoencoder.score} if autoencoder is not None else {}
        loaders, flags = self._loaders(source, pl_module.device, pl_module.dtype)
        was_training = pl_module.training
        pl_module.eval()
        with torch.inference_mode():
            sets = score_sets(pl_module, loaders, flags, scores, input_scores)
        pl_module.train(was_training)
        frame = rejection_table(sets, scores, self.quantiles, self.table)
        self._write(trainer, pl_module, scores, sets, frame)

    def _write(self, trainer, module, scores, sets, frame) -> None:
        from rotlearn.ood.report import log_tensorboard, write_tables, write_thresholds

        run_dir = Path(trainer.default_root_dir)
        rep = getattr(module.head, "name", type(module.head).__name__)
        frame.insert(0, "rep", rep)
        log.info("OOD evaluation: %s", write_tables(run_dir, rep, frame))
        checkpoints = getattr(trainer.checkpoint_callback, "dirpath", None)
        ood = calibrated_threshold(frame, "dt")
        if ood is not None and checkpoints and Path(checkpoints).is_dir():
            write_thresholds(checkpoints, ood)
        for logger in trainer.loggers:
            if isinstance(logger, TensorBoardLogger):
                log_tensorboard(logger.experiment, scores, sets, frame, trainer.global_step)
