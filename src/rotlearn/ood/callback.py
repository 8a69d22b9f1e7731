"""`callbacks=ood`: OOD evaluation at test time (paper section V-A, Table I, Fig. 6-8).

After the regular test, the callback scores the TRAINING set (unshuffled, unaugmented), sets a
threshold per score and quantile (`rotlearn.ood.scores.quantile_threshold`), and evaluates the
clean test set and the same test set with its last `corrupt_fraction` randomly erased. It writes
`ood.csv` (one row per score, quantile and test set) and a Table I-style `ood.md` to the run
directory, and logs scalars and figures (precision-recall curve over q, score-vs-error scatter,
box plots of the score on train / test / corrupted / pure-noise inputs) to TensorBoard.
"""

from __future__ import annotations

import functools
import logging
import math
import os
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
from rotlearn.geometry import angle_deg
from rotlearn.io import write_text_atomic
from rotlearn.ood.evaluation import rejection_row
from rotlearn.ood.scores import SCORES, Score, available_scores
from rotlearn.trust import config_target

__all__ = ["OODEvaluation", "pr_quantiles"]

log = logging.getLogger("rotlearn")


def pr_quantiles(start: float = 0.05, stop: float = 0.97, step: float = 0.02) -> list[float]:
    """The quantiles of the precision-recall curve: 0.05 to 0.97 by 0.02."""
    return [round(q, 6) for q in np.arange(start, stop + step / 2, step)]


@config_target
class OODEvaluation(pl.Callback):
    """Score, threshold and evaluate OOD rejection when the test loop ends (module docstring).

    Args:
        quantiles: fractions of the training scores kept, each in [0, 1] (paper: 0.75 KITTI,
            0.5 MAV, 1.0 for the auto-encoder).
        scores: among dt, eigengap, raw_norm, autoencoder; those the head cannot give (dt and
            eigengap need the A head) or that lack a checkpoint (autoencoder) are skipped.
        autoencoder_ckpt: checkpoint of `rotlearn-train experiment=<data>_autoencoder`.
        autoencoder_train: without a checkpoint, train an auto-encoder here first, on the same
            training pairs: {epochs, lr, and ConvAutoEncoder's channels, hidden, latent}; it is
            saved as `<run>/autoencoder.ckpt` (reusable as `autoencoder_ckpt`). For demos; on
            real data train it once with its experiment instead.
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

    # -- collecting scores ---------------------------------------------------------------------

    def _autoencoder(self, trainer: pl.Trainer, device: torch.device):
        from rotlearn.lit.autoencoder import load_autoencoder

        if "autoencoder" not in self.score_names:
            return None
        if self.autoencoder_ckpt:
            return load_autoencoder(self.autoencoder_ckpt, device=device)
        if self.autoencoder_train:
            return load_autoencoder(self._train_autoencoder(trainer, device), device=device)
        return None

    def _train_autoencoder(self, trainer: pl.Trainer, device: torch.device) -> Path:
        """Fit an auto-encoder on the datamodule's training pairs; returns its checkpoint."""
        from hydra.utils import instantiate

        from rotlearn.lit.autoencoder import AutoEncoderModule

        dm = trainer.datamodule
        spec = dict(self.autoencoder_train)
        epochs, lr = int(spec.pop("epochs", 20)), float(spec.pop("lr", 5e-4))
        pairs = dm.sets["test"].__getitems__([0])["input"]
        net_cfg = {"_target_": "rotlearn.nets.ConvAutoEncoder", "pair_channels": pairs.shape[1],
                   "image_size": pairs.shape[-1], **spec}  # fmt: skip
        module = AutoEncoderModule(instantiate(net_cfg)).to(device)
        module.run_config = {"task": "autoencoder", "net": net_cfg}
        optimizer = torch.optim.Adam(module.parameters(), lr=lr)
        log.info("OOD evaluation: training an auto-encoder for %d epochs", epochs)
        module.train()
        for _ in range(epochs):  # the paper's loop (section VI-C.1): Adam on the mean L1 error
            for batch in dm.train_dataloader():
                batch = dm.on_after_batch_transfer({k: v.to(device) for k, v in batch.items()}, 0)
                loss = module.errors(batch["input"]).mean()
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
        path = Path(trainer.default_root_dir) / "autoencoder.ckpt"
        tmp = path.with_name(f".{path.name}.tmp")
        torch.save({"state_dict": module.state_dict(), "rotlearn_config": module.run_config}, tmp)
        os.replace(tmp, path)
        return path

    def _score_batch(
        self, module, autoencoder, scores: list[Score], batch: dict
    ) -> dict[str, Tensor]:
        prediction = module(batch["input"])
        out = {"error": angle_deg(prediction.R, batch["R"]).double()}
        for score in scores:
            values = autoencoder.score(batch["input"]) if score.fn is None else score.fn(prediction)
            out[score.name] = values.double()
        return out

    @staticmethod
    def _on_device(dm, batch: dict[str, Tensor], device: torch.device) -> dict[str, Tensor]:
        """A loader batch as the model sees it: on its device, through the datamodule's hook."""
        return dm.on_after_batch_transfer({k: v.to(device) for k, v in batch.items()}, 0)

    @staticmethod
    def _batch_loader(dm, split: str, batches: list[list[int]]) -> torch.utils.data.DataLoader:
        """The pairs of `split` in the given batches of indices, in that order."""
        collate = dm.eval_loader(split).collate_fn
        return torch.utils.data.DataLoader(
            dm.sets[split], batch_sampler=batches, collate_fn=collate
        )

    def _unseen(self, dm, split: str) -> Tensor:
        """(sources,) bool: which sequences / scenes of `split` the model was not trained on,
        when `unseen_scenes_ood` (MAV: indoor and transition are OOD); else all False."""
        names = dm.sets[split].index.names
        trained = set(dm.sets["train"].index.names)
        return torch.tensor([self.unseen_scenes_ood and n not in trained for n in names] or [False])

    def _collect(self, trainer, module, autoencoder, scores, split, loader, corrupt=None):
        """Errors and scores of every pair of `loader`; `corrupted` (the OOD label) is set for
        erased pairs (`corrupt`, by test index) and pairs from unseen scenes."""
        dm = trainer.datamodule
        unseen = self._unseen(dm, split)
        parts: list[dict[str, Tensor]] = []
        for batch in loader:
            erase = torch.zeros_like(batch["corrupted"])
            if corrupt is not None:
                erase = corrupt[batch["index"]]
            batch = self._on_device(dm, {**batch, "corrupted": erase}, module.device)
            erase = batch["corrupted"]
            part = self._score_batch(module, autoencoder, scores, batch)
            part["corrupted"] = erase | unseen.to(erase.device)[batch["source"]]
            parts.append({k: v.cpu() for k, v in part.items()})
        return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}

    def _noise(self, trainer, module, autoencoder, scores) -> dict[str, Tensor]:
        dm = trainer.datamodule
        sample = dm.sets["test"].__getitems__([0])
        shape = (self.noise_pairs, *sample["input"].shape[1:])
        generator = torch.Generator().manual_seed(dm.seed + 99)
        noise = torch.randint(0, 256, shape, generator=generator, dtype=torch.uint8)
        n = self.noise_pairs
        batch = {
            "input": noise,
            "R": torch.eye(3).expand(n, 3, 3),
            "q": torch.tensor([0.0, 0.0, 0.0, 1.0]).expand(n, 4),
            "corrupted": torch.zeros(n, dtype=torch.bool),
            "boxes": torch.zeros(n, 2, 4, dtype=torch.long),
        }
        batch = self._on_device(dm, batch, module.device)
        return {
            k: v.cpu() for k, v in self._score_batch(module, autoencoder, scores, batch).items()
        }

    # -- the evaluation --------------------------------------------------------------------------

    def on_test_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        dm = trainer.datamodule
        if not hasattr(dm, "eval_loader"):
            raise ConfigValueError(
                "callbacks.ood", "needs an image-pair datamodule (data=kitti or data=mav)"
            )
        if not trainer.is_global_zero:
            return
        # the test loop runs in inference mode; training an auto-encoder here needs autograd
        with torch.inference_mode(False), torch.enable_grad():
            autoencoder = self._autoencoder(trainer, pl_module.device)
        was_training = pl_module.training
        pl_module.eval()
        with torch.inference_mode():
            results = self._evaluate(trainer, pl_module, autoencoder)
        pl_module.train(was_training)
        self._write(trainer, pl_module, *results)

    def _evaluate(self, trainer, module, autoencoder):
        dm = trainer.datamodule
        scores = available_scores(
            self.score_names, module.head.defines_belief, autoencoder is not None
        )
        n_train, n_test = len(dm.sets["train"]), len(dm.sets["test"])
        train_loader = dm.eval_loader("train")
        if self.max_train_pairs and n_train > self.max_train_pairs:
            keep = np.linspace(0, n_train - 1, self.max_train_pairs).astype(int).tolist()
            batches = [
                keep[i : i + dm.eval_batch_size] for i in range(0, len(keep), dm.eval_batch_size)
            ]
            train_loader = self._batch_loader(dm, "train", batches)
        collect = functools.partial(self._collect, trainer, module, autoencoder, scores)
        sets = {"train": collect("train", train_loader)}
        sets["clean"] = collect("test", dm.eval_loader("test"))
        # the corrupted set is the clean one, with the test batches that hold erased pairs
        # scored again (the same batches as in the clean pass; the others are not rerun)
        flags = corrupted_flags(n_test, self.corrupt_fraction)
        size = dm.eval_batch_size
        batches = [list(range(i, min(i + size, n_test))) for i in range(0, n_test, size)]
        batches = [b for b in batches if flags[b].any()]
        redone = collect("test", self._batch_loader(dm, "test", batches), flags)
        rows = torch.tensor([i for b in batches for i in b], dtype=torch.long)
        sets["corrupted"] = {k: v.clone() for k, v in sets["clean"].items()}
        for key, values in redone.items():
            sets["corrupted"][key][rows] = values
        sets["noise"] = self._noise(trainer, module, autoencoder, scores)
        rows = []
        for score in scores:
            nan_count = {k: int((~torch.isfinite(v[score.name])).sum()) for k, v in sets.items()}
            if any(nan_count.values()):
                log.warning("OOD score %s is NaN or inf for %s samples (never kept)", score.name,
                            nan_count)  # fmt: skip
            for test_set in ("clean", "corrupted"):
                data = sets[test_set]
                for q in sorted(set(self.quantiles) | {self._table_q(score.name)}):
                    row = rejection_row(
                        score, q, sets["train"][score.name], data[score.name], data["error"],
                        data["corrupted"],
                    )  # fmt: skip
                    rows.append({"set": test_set, "in_table": q == self._table_q(score.name),
                                 **row})  # fmt: skip
        return scores, sets, rows

    def _table_q(self, name: str) -> float:
        if name in self.table:
            return float(self.table[name])
        below = [q for q in self.quantiles if q <= 0.75]
        return max(below) if below else min(self.quantiles)

    # -- outputs ---------------------------------------------------------------------------------

    def _write(self, trainer, module, scores, sets, rows) -> None:
        import pandas as pd

        from rotlearn.ood.report import ood_markdown

        run_dir = Path(trainer.default_root_dir)
        rep = getattr(module.head, "name", type(module.head).__name__)
        frame = pd.DataFrame(rows)
        frame.insert(0, "rep", rep)
        write_text_atomic(run_dir / "ood.csv", frame.to_csv(index=False))
        write_text_atomic(run_dir / "ood.md", ood_markdown(rep, frame))
        log.info("OOD evaluation: %s", run_dir / "ood.md")
        self._calibrate_checkpoints(run_dir, frame)
        for logger in trainer.loggers:
            if isinstance(logger, TensorBoardLogger):
                self._log_tensorboard(logger.experiment, scores, sets, frame, trainer.global_step)

    def _calibrate_checkpoints(self, run_dir: Path, frame) -> None:
        """Store the DT threshold at its Table I quantile in the run's checkpoints, so that
        `rotlearn.load(...)` returns keep flags (`rotlearn_ood`)."""
        from rotlearn.checkpoint import load_checkpoint

        rows = frame[(frame["score"] == "dt") & frame["in_table"] & (frame["set"] == "clean")]
        if rows.empty:
            return
        ood = {"score": "dt", "threshold": float(rows["threshold"].iloc[0]),
               "q": float(rows["q"].iloc[0])}  # fmt: skip
        for path in sorted((run_dir / "checkpoints").glob("*.ckpt")):
            checkpoint = load_checkpoint(path)
            checkpoint["rotlearn_ood"] = ood
            tmp = path.with_name(f".{path.name}.tmp")
            torch.save(checkpoint, tmp)
            os.replace(tmp, path)

    def _log_tensorboard(self, writer, scores, sets, frame, step: int) -> None:
        from rotlearn.ood.report import box_figure, pr_figure, scatter_figure

        for row in frame.itertuples():
            prefix = f"ood/{row.score}/q{row.q:g}/{row.set}"
            for key in ("kept_pct", "err_mean_kept", "precision", "recall", "auroc", "spearman"):
                value = getattr(row, key)
                if not (isinstance(value, float) and math.isnan(value)):
                    writer.add_scalar(f"{prefix}/{key}", value, step)
        for score in scores:
            curve = [
                rejection_row(score, q, sets["train"][score.name], sets["corrupted"][score.name],
                              sets["corrupted"]["error"], sets["corrupted"]["corrupted"])
                for q in pr_quantiles()
            ]  # fmt: skip
            writer.add_figure(f"ood/{score.name}/precision_recall", pr_figure(score, curve), step)
            writer.add_figure(f"ood/{score.name}/score_vs_error", scatter_figure(score, sets), step)
            writer.add_figure(f"ood/{score.name}/boxes", box_figure(score, sets), step)
        writer.flush()
