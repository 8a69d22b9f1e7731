"""The OOD evaluation as pure functions (paper section V-A, Table I): no Lightning, no files.

`evaluate(predict_fn, loaders, flags, ...)` scores every sample of every set (`score_sets`) and
tabulates rejection at each quantile threshold of a reference set's scores (`rejection_table`):
the validation set by default (held-out pairs of the training side, `callbacks.ood.
thresholds_from: val`), or the training set (the paper's protocol, section V-A: `train`). For one
score on one test set (`rejection_row`): kept %, the error (mean, median) of the kept and of all
samples, precision = |kept and clean| / |kept| (the paper's Table I "Precision": its numbers fit
this, not its footnote), recall = |kept and clean| / |clean|, the % of OOD samples rejected, the
AUROC of the score for telling OOD from clean samples, and the Spearman correlation of the score
with the error. `precision_recall_curve` is the same row over many quantiles; `mixed_set` appends
an extra evaluation set (e.g. pairs of unseen scenes) to the test set, flagged OOD.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from rotlearn.geometry import angle_deg
from rotlearn.heads import RotationPrediction
from rotlearn.scores import Score, auroc, keep_mask, quantile_threshold, spearman

if TYPE_CHECKING:
    import pandas as pd

__all__ = [
    "REFERENCE_SETS",
    "TEST_SETS",
    "calibrated_threshold",
    "evaluate",
    "mixed_set",
    "pr_quantiles",
    "precision_recall_curve",
    "reference_set",
    "rejection_row",
    "rejection_table",
    "score_sets",
    "table_quantile",
]

log = logging.getLogger("rotlearn")

TEST_SETS = ("clean", "corrupted")
REFERENCE_SETS = ("val", "train")  # where quantile thresholds may come from (default first)


def _stats(errors: Tensor) -> tuple[float, float]:
    if errors.numel() == 0:
        return math.nan, math.nan
    return float(errors.mean()), float(errors.median())


def rejection_row(
    score: Score,
    q: float,
    train_scores: Tensor,
    scores: Tensor,
    errors: Tensor,
    corrupted: Tensor,
) -> dict[str, float | int | str]:
    """The statistics of keeping the samples on the confident side of the q-threshold.

    Args:
        score: which score (for its direction).
        q: quantile of the reference scores (`quantile_threshold`).
        train_scores: (N_ref,) scores of the reference set (validation or training).
        scores, errors, corrupted: (N,) scores, errors in degrees and flags of the test set.

    Returns:
        A flat dict: score, q, threshold, n, n_corrupted, nan_scores, kept_pct, err_mean_all,
        err_median_all, err_mean_kept, err_median_kept, precision, recall, ood_rejected (percent
        of the OOD samples not kept; NaN where undefined), auroc and spearman (score vs error).
    """
    threshold = quantile_threshold(train_scores, q, score.keep_below)
    kept = keep_mask(scores, threshold, score.keep_below)
    clean = ~corrupted
    n_kept, n_clean, n_ood = int(kept.sum()), int(clean.sum()), int(corrupted.sum())
    kept_clean = int((kept & clean).sum())
    rejected_ood = int((~kept & corrupted).sum())
    mean_all, median_all = _stats(errors.double())
    mean_kept, median_kept = _stats(errors[kept].double())
    return {
        "score": score.name,
        "keep": "below" if score.keep_below else "above",
        "q": q,
        "threshold": threshold,
        "n": len(scores),
        "n_corrupted": int(corrupted.sum()),
        "nan_scores": int((~torch.isfinite(scores)).sum()),
        "kept_pct": 100.0 * n_kept / max(len(scores), 1),
        "err_mean_all": mean_all,
        "err_median_all": median_all,
        "err_mean_kept": mean_kept,
        "err_median_kept": median_kept,
        "precision": 100.0 * kept_clean / n_kept if n_kept else math.nan,
        "recall": 100.0 * kept_clean / n_clean if n_clean else math.nan,
        "ood_rejected": 100.0 * rejected_ood / n_ood if n_ood else math.nan,
        "auroc": auroc(scores, corrupted, score.keep_below),
        "spearman": spearman(scores, errors),
    }


def pr_quantiles(start: float = 0.05, stop: float = 0.97, step: float = 0.02) -> list[float]:
    """The quantiles of the precision-recall curve: 0.05 to 0.97 by 0.02."""
    return [round(q, 6) for q in np.arange(start, stop + step / 2, step)]


def precision_recall_curve(
    score: Score,
    train_scores: Tensor,
    test: Mapping[str, Tensor],
    quantiles: Sequence[float] | None = None,
) -> list[dict[str, float | int | str]]:
    """`rejection_row` of `score` on one flagged test set at each quantile (default
    `pr_quantiles()`): the precision-recall curve over q.

    Args:
        score: the score.
        train_scores: (N_ref,) its reference scores (the thresholds: validation or training).
        test: a flagged set of `score_sets`: {"error", "corrupted", score.name: (N,)}.
        quantiles: the q values, each in [0, 1].
    """
    qs = pr_quantiles() if quantiles is None else quantiles
    return [
        rejection_row(score, q, train_scores, test[score.name], test["error"], test["corrupted"])
        for q in qs
    ]


def mixed_set(base: Mapping[str, Tensor], extra: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """A test set followed by an extra set whose samples all count as OOD (paper Fig. 8: the
    outdoor test pairs, then those of the unseen indoor scene).

    Args:
        base: a flagged set of `score_sets` ({"error", "corrupted", scores...}, (N,) each).
        extra: a set of `score_sets` with the same keys (its own "corrupted" flags are ignored).

    Returns:
        {key: (N + M,)}: `base` then `extra`, "corrupted" True on the M extra samples.

    Raises:
        ValueError: if the two sets have different keys.
    """
    keys = set(base) - {"corrupted"}
    if keys != set(extra) - {"corrupted"}:
        raise ValueError(f"cannot mix sets with keys {sorted(base)} and {sorted(extra)}")
    mixed = {k: torch.cat([base[k], extra[k]]) for k in keys}
    ood = torch.ones(len(extra["error"]), dtype=torch.bool)
    mixed["corrupted"] = torch.cat([base["corrupted"].bool(), ood])
    return mixed


def table_quantile(name: str, table: Mapping[str, float], quantiles: Sequence[float]) -> float:
    """The quantile at which score `name` enters Table I: `table[name]`, else the largest of
    `quantiles` <= 0.75 (else their smallest)."""
    if name in table:
        return float(table[name])
    below = [q for q in quantiles if q <= 0.75]
    return max(below) if below else min(quantiles)


Batch = Mapping[str, Tensor]


def score_sets(
    predict_fn: Callable[[Tensor], RotationPrediction],
    loaders: Mapping[str, Iterable[Batch]],
    flags: Mapping[str, Tensor],
    scores: Sequence[Score],
    input_scores: Mapping[str, Callable[[Tensor], Tensor]] | None = None,
) -> dict[str, dict[str, Tensor]]:
    """Every sample's error and scores, set by set.

    Args:
        predict_fn: (B, ...) inputs -> a `RotationPrediction` (call it in eval mode, without
            gradients).
        loaders: set name -> finished batches {"input", "R" (B, 3, 3)} (on the model's device,
            in its dtype), e.g. "train", "clean", "corrupted", "noise".
        flags: test-set name -> (N,) bool, in loader order: which samples are OOD (erased, or
            from scenes not trained on).
        scores: the scores; those without `fn` (the auto-encoder) are read from `input_scores`.
        input_scores: score name -> (B, ...) inputs -> (B,) scores.

    Returns:
        set name -> {"error": (N,) degrees, one (N,) entry per score, and for the sets in `flags`
        "corrupted": (N,) bool}, float64 on the CPU.
    """
    input_scores = dict(input_scores or {})
    sets: dict[str, dict[str, Tensor]] = {}
    for name, batches in loaders.items():
        parts: list[dict[str, Tensor]] = []
        for batch in batches:
            prediction = predict_fn(batch["input"])
            part = {"error": angle_deg(prediction.R, batch["R"]).double()}
            for score in scores:
                if score.fn is not None:
                    values = score.fn(prediction)
                else:
                    values = input_scores[score.name](batch["input"])
                part[score.name] = values.double()
            parts.append({k: v.cpu() for k, v in part.items()})
        sets[name] = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
        if name in flags:
            label = flags[name].bool().cpu()
            if label.shape != sets[name]["error"].shape:
                raise ValueError(
                    f"flags[{name!r}] has shape {tuple(label.shape)}, but the set holds "
                    f"{len(sets[name]['error'])} samples"
                )
            sets[name]["corrupted"] = label
    return sets


def rejection_table(
    sets: Mapping[str, Mapping[str, Tensor]],
    scores: Sequence[Score],
    quantiles: Sequence[float],
    table: Mapping[str, float] | None = None,
    reference: str = "val",
) -> pd.DataFrame:
    """One `rejection_row` per score, test set and quantile, thresholds from the `reference` set.

    Args:
        sets: `score_sets`' output.
        scores: the scores to tabulate.
        quantiles: fractions of the reference scores kept, each in [0, 1].
        table: score -> its Table I quantile (`table_quantile`), evaluated too.
        reference: the set the thresholds come from ("val": held-out pairs of the training
            side; "train": the training pairs, the paper's protocol).

    Returns:
        Columns set, in_table (whether the row is the score's Table I row), thresholds_from
        (`reference`), and those of
        `rejection_row`; ordered by score, test set, quantile. The test sets are those of
        `TEST_SETS` that are present, then every other set with "corrupted" flags (extra
        evaluation sets, e.g. `mixed_set`), in their order.
    """
    import pandas as pd

    table = dict(table or {})
    test_sets = [name for name in TEST_SETS if name in sets]
    test_sets += [n for n, v in sets.items() if n not in test_sets and "corrupted" in v]
    rows: list[dict[str, Any]] = []
    for score in scores:
        nan_count = {k: int((~torch.isfinite(v[score.name])).sum()) for k, v in sets.items()}
        if any(nan_count.values()):
            log.warning("OOD score %s is NaN or inf for %s samples (never kept)", score.name,
                        nan_count)  # fmt: skip
        table_q = table_quantile(score.name, table, quantiles)
        for test_set in test_sets:
            data = sets[test_set]
            for q in sorted(set(quantiles) | {table_q}):
                row = rejection_row(
                    score, q, sets[reference][score.name], data[score.name], data["error"],
                    data["corrupted"],
                )  # fmt: skip
                rows.append({"set": test_set, "in_table": q == table_q,
                             "thresholds_from": reference, **row})  # fmt: skip
    return pd.DataFrame(rows)


def reference_set(frame: pd.DataFrame) -> str:
    """The set whose scores gave `frame`'s thresholds (its thresholds_from column; "train" for
    tables written before validation thresholds existed)."""
    if "thresholds_from" in frame.columns and len(frame):
        return str(frame["thresholds_from"].iloc[0])
    return "train"


def evaluate(
    predict_fn: Callable[[Tensor], RotationPrediction],
    loaders: Mapping[str, Iterable[Batch]],
    flags: Mapping[str, Tensor],
    scores: Sequence[Score],
    quantiles: Sequence[float],
    table: Mapping[str, float] | None = None,
    input_scores: Mapping[str, Callable[[Tensor], Tensor]] | None = None,
    reference: str = "val",
) -> pd.DataFrame:
    """The OOD evaluation: `rejection_table(score_sets(...))` (see both for the arguments).

    `loaders` needs the `reference` set (the thresholds: "val" or "train") and the test sets
    "clean" and / or "corrupted", each with its `flags`.
    """
    sets = score_sets(predict_fn, loaders, flags, scores, input_scores)
    return rejection_table(sets, scores, quantiles, table, reference)


def calibrated_threshold(frame: pd.DataFrame, score: str = "dt") -> dict[str, Any] | None:
    """{"score", "threshold", "q", "reference"} of `score`'s Table I row on the clean test set
    (the threshold `rotlearn.load` applies for keep flags; `reference`: the set whose scores
    gave it, "val" or "train"), or None if the table has none."""
    rows = frame[(frame["score"] == score) & frame["in_table"] & (frame["set"] == "clean")]
    if rows.empty:
        return None
    return {"score": score, "threshold": float(rows["threshold"].iloc[0]),
            "q": float(rows["q"].iloc[0]), "reference": reference_set(frame)}  # fmt: skip
