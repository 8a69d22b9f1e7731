"""`callbacks=ood`: OOD evaluation at test time (paper section V-A, Table I, Fig. 6-8).

A thin callback: after the regular test, it reads the datamodule through `OODDataSource`, scores
the reference set of the thresholds (`thresholds_from`: the VALIDATION pairs, held out from the
training side, by default; the TRAINING pairs, unshuffled and unaugmented, as in the paper), the
clean test set and the same test set with its last
`corrupt_fraction` randomly erased, pure-noise pairs, and each extra evaluation set (`extra_sets`:
the test split of a copy of the datamodule with some settings changed, e.g. unseen scenes, appended
to the clean test set and counted as OOD) (`rotlearn.ood.evaluation`), then writes `ood.csv` and a
Table I-style `ood.md` to the run directory, every sample's error and scores (`ood_samples.csv`,
for `rotlearn-report`'s figures), a grid of erased example pairs with their scores
(`ood_examples.png`), the calibrated DT threshold beside the run's checkpoints
(`ood_thresholds.json`, read by `rotlearn.load` for keep flags) (`rotlearn.ood.records`), and, in
a `TensorBoardRunLogger`, one figure per score and the examples (`rotlearn.report.figures`, which
`rotlearn-report` draws with too). Each score's AUROC on the corrupted set, `ood/auroc_<score>`,
is one of the run's results (`results`, read by `rotlearn.lit.RunRecords`: metrics.json and
TensorBoard's HPARAMS view); no per-quantile scalars. Scoring shows a progress bar when it takes
more than two seconds.
"""

from __future__ import annotations

import copy
import functools
import logging
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import lightning.pytorch as pl
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from rotlearn.data.corruption import corrupted_flags, erase_boxes
from rotlearn.errors import ConfigError
from rotlearn.logs import progress
from rotlearn.ood.evaluation import (
    REFERENCE_SETS,
    calibrated_threshold,
    mixed_set,
    rejection_table,
    score_sets,
)
from rotlearn.ood.source import OODDataSource
from rotlearn.paths import OOD_EXAMPLES_FILE
from rotlearn.scores import SCORES, available_scores
from rotlearn.trust import config_target

if TYPE_CHECKING:  # constraints of the config values, checked by rotlearn.config
    from annotated_types import Ge, Gt, Le, MinLen

__all__ = ["OODEvaluation", "extra_source"]

log = logging.getLogger("rotlearn")
RESERVED_SETS = ("train", "val", "clean", "corrupted", "noise")
FILE_SETTINGS = ("root", "cache_dir")  # an extra set reads the run's own dataset and cache


def check_settings(source: Any, name: str, overrides: dict[str, Any]) -> None:
    """Raise `ConfigError` (key `extra_sets.<name>.<setting>`) for a setting that the
    datamodule `source` does not have."""
    for key in overrides:
        if key.startswith("_") or not hasattr(source, key) or callable(getattr(source, key)):
            raise ConfigError(
                f"extra_sets.{name}.{key}", f"{type(source).__name__} has no setting {key!r}"
            )


def extra_source(source: Any, name: str, overrides: dict[str, Any]) -> Any:
    """A set-up copy of the image-pair datamodule `source` with some of its settings changed
    (`OODEvaluation(extra_sets=...)`): its test split is an extra evaluation set. Its training
    split stays that of `source`, so `unseen_pairs` still compares with what was trained on.

    Raises:
        ConfigError: (key `extra_sets.<name>.<setting>`) if `source` has no such setting.
    """
    check_settings(source, name, overrides)
    extra = copy.copy(source)
    for key, value in overrides.items():
        setattr(extra, key, list(value) if isinstance(value, (list, tuple)) else value)
    extra.sets = {}  # `setup` builds the splits again from the changed settings
    extra.setup("test")
    return extra


@config_target
class OODEvaluation(pl.Callback):
    """Score, threshold and evaluate OOD rejection when the test loop ends (module docstring).

    Args:
        quantiles: fractions of the reference scores kept, each in [0, 1] (paper: 0.75 KITTI,
            0.5 MAV, 1.0 for the auto-encoder).
        thresholds_from: the reference set of the quantile thresholds: "val" (the validation
            pairs, held out from the training side: new pairs of the training distribution,
            so about q of new clean pairs pass) or "train" (the training pairs: the paper's
            protocol, section V-A; a model fits them more closely than new pairs, so fewer
            than q of new clean pairs pass).
        scores: among dt, eigengap, raw_norm, autoencoder, disagreement; those the head cannot
            give (dt and eigengap need a belief, disagreement an ensemble) or that lack a
            checkpoint (autoencoder) are skipped.
        autoencoder_ckpt: checkpoint (or run directory) of an auto-encoder trained as its own
            run, `rotlearn-train experiment=<data>_autoencoder` (the demos:
            `experiment=kitti_autoencoder_demo`, `mav_autoencoder_demo`); without it the
            `autoencoder` score is skipped. It is never trained here, inside a test.
        corrupt_fraction: the last fraction of the test set that is erased for the corrupted set.
        table: score -> quantile shown in `ood.md`'s Table I (others: the largest quantile <= 0.75);
            these quantiles are evaluated too.
        noise_pairs: pure-noise input pairs scored for the box plots.
        max_train_pairs: with thresholds_from=train, score at most this many training pairs
            (evenly spaced); null: all.
        unseen_scenes_ood: count test pairs from sequences / scenes absent from training as OOD
            (with the erased ones) in precision, recall and AUROC: the MAV experiment, where
            the indoor and transition scenes are the unseen environments (paper Fig. 8).
        extra_sets: {name: {datamodule setting: value}}: for each, the test split of a copy of
            the datamodule with those settings (e.g. `{indoor: {test_scenes: [indoor]}}` for
            MAV, `{unseen: {test_sequences: ["01"]}}` for KITTI) is scored, appended to the clean
            test set with every one of its pairs counted as OOD, and tabulated as the set `name`
            (paper Fig. 8: outdoor, + indoor, + transition from one model).
        examples: erased test pairs (and a third as many clean ones) drawn with their scores in
            `ood_examples.png`; 0: none.
    """

    # What a run config must hold for this callback, (key, class, what) read from this source by
    # `rotlearn.config` before anything is imported: its datamodule defines OODDataSource's methods.
    config_needs = (
        (
            "data",
            "rotlearn.ood.source.OODDataSource",
            "an image-pair datamodule (an OODDataSource: data=kitti or data=mav)",
        ),
    )

    def __init__(
        self,
        quantiles: Annotated[list[Annotated[float, Ge(0), Le(1)]], MinLen(1)] = (
            0.25,
            0.5,
            0.75,
            1.0,
        ),
        scores: list[str] = ("dt", "eigengap", "raw_norm", "autoencoder", "disagreement"),
        autoencoder_ckpt: str | None = None,
        corrupt_fraction: Annotated[float, Gt(0), Le(1)] = 0.5,
        table: dict[str, Annotated[float, Ge(0), Le(1)]] | None = None,
        noise_pairs: Annotated[int, Ge(0)] = 64,
        max_train_pairs: Annotated[int, Gt(0)] | None = None,
        unseen_scenes_ood: bool = False,
        extra_sets: dict[str, dict[str, Any]] | None = None,
        examples: Annotated[int, Ge(0)] = 6,
        thresholds_from: str = "val",
    ) -> None:
        super().__init__()
        if thresholds_from not in REFERENCE_SETS:
            raise ConfigError(
                "thresholds_from", f"must be one of {list(REFERENCE_SETS)}, got {thresholds_from!r}"
            )
        self.thresholds_from = thresholds_from
        self.quantiles = [float(q) for q in quantiles]
        unknown = sorted(set(scores) - set(SCORES))
        if unknown:
            raise ConfigError("scores", f"unknown {unknown}; choose from {sorted(SCORES)}")
        if autoencoder_ckpt and not Path(autoencoder_ckpt).exists():
            raise ConfigError("autoencoder_ckpt", f"{autoencoder_ckpt} does not exist")
        self.score_names = list(scores)
        self.autoencoder_ckpt = autoencoder_ckpt
        self.corrupt_fraction = float(corrupt_fraction)
        self.table = {"autoencoder": 1.0, **(table or {})}
        self.noise_pairs, self.max_train_pairs = int(noise_pairs), max_train_pairs
        self.unseen_scenes_ood = bool(unseen_scenes_ood)
        if isinstance(extra_sets, DictConfig):
            extra_sets = OmegaConf.to_container(extra_sets, resolve=True)
        self.extra_sets = dict(extra_sets or {})
        for name, overrides in self.extra_sets.items():
            if name in RESERVED_SETS or not isinstance(overrides, dict) or not overrides:
                raise ConfigError(
                    f"extra_sets.{name}",
                    f"needs a name other than {list(RESERVED_SETS)} and a non-empty mapping of "
                    f"datamodule settings (e.g. {{test_scenes: [indoor]}}), got {overrides!r}",
                )
            for key in (k for k in overrides if k in FILE_SETTINGS):
                raise ConfigError(
                    f"extra_sets.{name}.{key}",
                    "an extra set tests other scenes or sequences of the run's own dataset and "
                    "cache (data.root, data.cache_dir); it names no files",
                )
        self.examples = int(examples)
        self.results: dict[str, float] = {}  # the run's one-shot results (RunRecords)

    def _autoencoder(self, device: torch.device) -> Any:
        """The auto-encoder net of the `autoencoder` score, from `autoencoder_ckpt`, or None."""
        from rotlearn.nets.autoencoder import load_autoencoder_net

        if "autoencoder" not in self.score_names or not self.autoencoder_ckpt:
            return None
        return load_autoencoder_net(self.autoencoder_ckpt, device=device)

    def _loaders(
        self, source: OODDataSource, device: torch.device, dtype: torch.dtype
    ) -> tuple[dict[str, Iterable[dict[str, Tensor]]], dict[str, Tensor]]:
        """Finished batches of the reference (val or train), clean, corrupted and noise sets, and
        the OOD flags of the test sets (erased pairs, and pairs from unseen scenes when
        `unseen_scenes_ood`)."""
        reference = self.thresholds_from
        n_ref, n_test = source.pair_count(reference), source.pair_count("test")
        if n_ref == 0:
            raise ConfigError(
                "callbacks.ood.thresholds_from",
                f"{reference}: the datamodule has no {reference} pairs to take thresholds from "
                "(data.val_fraction=0 and no data.val_sequences?)",
            )
        keep = None
        if reference == "train" and self.max_train_pairs and n_ref > self.max_train_pairs:
            keep = np.linspace(0, n_ref - 1, self.max_train_pairs).astype(int).tolist()
        erase = corrupted_flags(n_test, self.corrupt_fraction)
        unseen = source.unseen_pairs("test") & self.unseen_scenes_ood
        finish = functools.partial(source.finish_batch, device=device, dtype=dtype)
        loaders = {
            reference: map(finish, source.eval_loader(reference, indices=keep)),
            "clean": map(finish, source.eval_loader("test", erase=torch.zeros_like(erase))),
            "corrupted": map(finish, source.eval_loader("test", erase=erase)),
            "noise": [finish(source.noise_batch(self.noise_pairs))],
        }
        for name, overrides in self.extra_sets.items():
            extra = extra_source(source, name, overrides)
            clean = torch.zeros(extra.pair_count("test"), dtype=torch.bool)
            loaders[f"extra:{name}"] = map(finish, extra.eval_loader("test", erase=clean))
        return loaders, {"clean": unseen, "corrupted": erase | unseen}

    def _examples(self, source: OODDataSource, sets: dict[str, dict[str, Tensor]]):
        """(images, captions) of `examples` erased test pairs and a third as many clean ones,
        evenly spaced: uint8 (K, 2C, S, S) as erased, and per pair its error and scores."""
        flags = corrupted_flags(source.pair_count("test"), self.corrupt_fraction)
        erased = torch.nonzero(flags).flatten()
        clean = torch.nonzero(~flags).flatten()
        picks = []
        for pool, count in ((clean, -(-self.examples // 3)), (erased, self.examples)):
            if len(pool) and count:
                spots = np.unique(np.linspace(0, len(pool) - 1, min(count, len(pool))).astype(int))
                picks += pool[torch.from_numpy(spots)].tolist()
        if not picks:
            return None
        batches = list(source.eval_loader("test", indices=picks, erase=flags))
        images = torch.cat([erase_boxes(b["input"], b["boxes"], b["corrupted"]) for b in batches])
        keys = [k for k in sets["corrupted"] if k not in ("error", "corrupted")]
        captions = [
            {"erased": bool(flags[i]), "error": float(sets["corrupted"]["error"][i]),
             **{k: float(sets["corrupted"][k][i]) for k in keys}}
            for i in picks
        ]  # fmt: skip
        return images, captions

    def setup(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        """Check the extra sets' settings against the datamodule before anything is trained."""
        source = trainer.datamodule
        for name, overrides in self.extra_sets.items():
            check_settings(source, name, overrides)

    def on_test_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        source = trainer.datamodule
        if not isinstance(source, OODDataSource):
            raise ConfigError(
                "callbacks.ood", "needs an image-pair datamodule (data=kitti or data=mav)"
            )
        if not trainer.is_global_zero:
            return
        autoencoder = self._autoencoder(pl_module.device)
        scores = available_scores(
            self.score_names, pl_module.head.defines_belief, autoencoder is not None,
            pl_module.head.defines_members,
        )  # fmt: skip
        input_scores = {}
        if autoencoder is not None:
            input_scores["autoencoder"] = lambda x: autoencoder.reconstruction_error(
                x.to(pl_module.device, next(autoencoder.parameters()).dtype)
            )
        loaders, flags = self._loaders(source, pl_module.device, pl_module.dtype)
        loaders = {
            name: progress(batches, f"OOD scoring: {name.removeprefix('extra:')}", trainer)
            for name, batches in loaders.items()
        }
        was_training = pl_module.training
        pl_module.eval()
        with torch.inference_mode():
            sets = score_sets(pl_module, loaders, flags, scores, input_scores)
        pl_module.train(was_training)
        for name in self.extra_sets:
            sets[name] = mixed_set(sets["clean"], sets.pop(f"extra:{name}"))
        frame = rejection_table(sets, scores, self.quantiles, self.table, self.thresholds_from)
        examples = self._examples(source, sets) if self.examples else None
        self._write(trainer, pl_module, scores, sets, frame, examples)

    def _write(self, trainer, module, scores, sets, frame, examples) -> None:
        from rotlearn.ood.records import write_samples, write_tables, write_thresholds
        from rotlearn.report import figures

        run_dir = Path(trainer.default_root_dir)
        rep = getattr(module.head, "name", type(module.head).__name__)
        frame.insert(0, "rep", rep)
        log.info("OOD evaluation: %s", write_tables(run_dir, rep, frame))
        write_samples(run_dir, sets)
        example_figure = figures.examples_figure(*examples) if examples is not None else None
        if example_figure is not None:
            figures.save_figure(example_figure, run_dir / OOD_EXAMPLES_FILE)
        checkpoints = getattr(trainer.checkpoint_callback, "dirpath", None)
        ood = calibrated_threshold(frame, "dt")
        if ood is not None and checkpoints and Path(checkpoints).is_dir():
            write_thresholds(checkpoints, ood)
        corrupted = frame[frame["set"] == "corrupted"]
        self.results = {
            f"ood/auroc_{score.name}": float(rows["auroc"].iloc[0])
            for score in scores
            if len(rows := corrupted[corrupted["score"] == score.name])
        }
        loggers = [lg for lg in trainer.loggers if hasattr(lg, "log_figure")]
        step = module.tested_epochs
        for score in scores if loggers else []:
            figure = score_figure(score, sets, self.thresholds_from)
            for logger in loggers:
                logger.log_figure(f"ood/{score.name}", figure, step)
        for logger in loggers if example_figure is not None else []:
            logger.log_figure("ood/examples", example_figure, step)


def score_figure(score: Any, sets: dict[str, dict[str, Tensor]], reference: str = "val") -> Any:
    """One figure of an OOD score (TensorBoard): precision-recall over q (thresholds from the
    `reference` set's scores) on each flagged set but the clean one, error against score on the
    half-erased set, score box plots (Fig. 6c)."""
    from rotlearn.ood.evaluation import precision_recall_curve
    from rotlearn.report import figures

    fig, axes = figures.grid(1, 3, size=(4.2, 3.6))
    for ax in axes[0]:
        ax.set_visible(True)
    flagged = [n for n, v in sets.items() if n != "clean" and "corrupted" in v]
    curves = {
        n: precision_recall_curve(score, sets[reference][score.name], sets[n]) for n in flagged
    }
    figures.pr_figure(curves, ax=axes[0][0], title=f"{score.name}: precision-recall over q")
    data = sets["corrupted"]
    figures.scatter_figure(
        score.name,
        score.keep_below,
        data["error"],
        data[score.name],
        data["corrupted"],
        ax=axes[0][1],
        title="half-erased test set",
    )
    figures.score_boxes_figure(
        score.name, score.keep_below, figures.box_groups(score.name, sets), ax=axes[0][2]
    )
    return fig
