"""Rejection statistics for one score on one test set (paper section V-A, Table I).

Given per-sample errors, scores, corrupted flags and a threshold: kept %, the error of the kept
and of all samples, precision = |kept and clean| / |kept|, recall = |kept and clean| / |clean|,
the AUROC of the score for telling corrupted from clean samples, and the Spearman correlation of
the score with the error. Pure torch; no Lightning.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from rotlearn.ood.scores import Score, keep_mask, quantile_threshold

__all__ = ["auroc", "rank", "rejection_row", "spearman"]


def rank(x: Tensor) -> Tensor:
    """Average ranks (1-based, ties share their mean rank) of a (N,) tensor, float64."""
    x = x.double()
    order = torch.argsort(x, stable=True)
    sorted_x = x[order]
    ranks = torch.empty_like(x)
    ranks[order] = torch.arange(1, len(x) + 1, dtype=torch.float64)
    _, inverse, counts = torch.unique_consecutive(sorted_x, return_inverse=True, return_counts=True)
    ends = torch.cumsum(counts, 0).double()
    mean_rank = ends - (counts.double() - 1) / 2  # mean of the ranks of each tie group
    ranks[order] = mean_rank[inverse]
    return ranks


def auroc(scores: Tensor, positive: Tensor, keep_below: bool) -> float:
    """Probability that a random positive (corrupted) sample looks LESS confident than a random
    negative (clean) one (ties count 1/2): 1 is a perfect detector, 0.5 chance. NaN if either
    class is empty. Non-finite scores are dropped."""
    finite = torch.isfinite(scores)
    s, p = scores[finite].double(), positive[finite]
    if not keep_below:
        s = -s
    n_pos, n_neg = int(p.sum()), int((~p).sum())
    if n_pos == 0 or n_neg == 0:
        return math.nan
    r = rank(s)
    return float((r[p].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def spearman(x: Tensor, y: Tensor) -> float:
    """Spearman rank correlation of finite pairs; NaN for fewer than 3 or constant inputs."""
    finite = torch.isfinite(x) & torch.isfinite(y)
    if int(finite.sum()) < 3:
        return math.nan
    rx, ry = rank(x[finite]), rank(y[finite])
    rx, ry = rx - rx.mean(), ry - ry.mean()
    denominator = (rx.square().sum() * ry.square().sum()).sqrt()
    return float((rx * ry).sum() / denominator) if denominator > 0 else math.nan


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
        q: quantile of the training scores (`quantile_threshold`).
        train_scores: (N_train,) scores of the training set.
        scores, errors, corrupted: (N,) scores, errors in degrees and flags of the test set.

    Returns:
        A flat dict: score, q, threshold, n, n_corrupted, nan_scores, kept_pct, err_mean_all,
        err_median_all, err_mean_kept, err_median_kept, precision, recall (percent; NaN where
        undefined), auroc and spearman (score vs error).
    """
    threshold = quantile_threshold(train_scores, q, score.keep_below)
    kept = keep_mask(scores, threshold, score.keep_below)
    clean = ~corrupted
    n_kept, n_clean = int(kept.sum()), int(clean.sum())
    kept_clean = int((kept & clean).sum())
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
        "auroc": auroc(scores, corrupted, score.keep_below),
        "spearman": spearman(scores, errors),
    }
