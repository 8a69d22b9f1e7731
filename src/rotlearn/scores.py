"""Floor 2: uncertainty scores of a prediction, each with its direction, the one quantile-threshold
rule, and the rank statistics of scores (AUROC, Spearman; through torchmetrics).

Below both the training glue (`rotlearn.lit`, which logs each score's rank statistics at test
time) and the OOD evaluation (`rotlearn.ood`, which thresholds them): neither imports the other.

A score maps a prediction to (B,) numbers. `keep_below` says which side is confident: DT's
tr(Lambda), the auto-encoder's reconstruction error and an ensemble's disagreement keep LOW
scores; the eigen-gap and the norm of the raw output keep HIGH scores (paper section V-A).

Thresholds: for a quantile q, the threshold is set so that a fraction q of a reference set's
scores falls on the kept side: the q-quantile of the reference scores for keep-below scores
(kept if score < threshold), the (1 - q)-quantile for keep-above scores (kept if score >
threshold). The reference set is the validation set by default (held-out pairs of the training
side: on new data from the training distribution about q is kept); the paper's protocol takes
the training scores (section V-A), which a model fits more closely than new data, so fewer than
q of new clean pairs pass. A NaN score is never kept.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from rotlearn.extras import require
from rotlearn.heads import RotationPrediction

require("train", "rotlearn.scores (rank statistics through torchmetrics)")

from torchmetrics.functional import spearman_corrcoef
from torchmetrics.functional.classification import binary_auroc

__all__ = [
    "SCORES",
    "Score",
    "auroc",
    "available_scores",
    "keep_mask",
    "quantile_threshold",
    "register_score",
    "spearman",
]


@dataclass(frozen=True)
class Score:
    """An OOD score: `fn(prediction) -> (B,)`, kept below (or above) a threshold."""

    name: str
    keep_below: bool
    fn: Callable[[RotationPrediction], Tensor] | None
    needs_eigenvalues: bool = False
    description: str = ""
    needs_members: bool = False


def dt(prediction: RotationPrediction) -> Tensor:
    """tr(Lambda) = sum of the dispersion coefficients, 3 l1 - l2 - l3 - l4 <= 0 (paper eq. 26)."""
    return prediction.dt


def first_eigengap(prediction: RotationPrediction) -> Tensor:
    """l2 - l1 >= 0, the gap that makes the mode unique."""
    return prediction.eigengap


def raw_norm(prediction: RotationPrediction) -> Tensor:
    """||raw network output||, for every head (the paper's remark in section V-A)."""
    return torch.linalg.vector_norm(prediction.raw, dim=-1)


def disagreement(prediction: RotationPrediction) -> Tensor:
    """The largest angle (degrees) between an ensemble member's rotation and the ensemble's."""
    return prediction.disagreement


SCORES: dict[str, Score] = {
    "dt": Score("dt", True, dt, True, "tr(Lambda), dispersion thresholding (A + DT)"),
    "eigengap": Score("eigengap", False, first_eigengap, True, "first eigen-gap l2 - l1"),
    "raw_norm": Score("raw_norm", False, raw_norm, False, "norm of the raw network output"),
    "autoencoder": Score("autoencoder", True, None, False, "auto-encoder L1 reconstruction error"),
    "disagreement": Score(
        "disagreement",
        True,
        disagreement,
        True,
        "largest angle between an ensemble member and the ensemble (deg)",
        needs_members=True,
    ),
}


def register_score(score: Score) -> Score:
    """Make `score` available by its name (`callbacks.ood.scores`); names are unique."""
    if score.name in SCORES:
        raise ValueError(f"an OOD score named {score.name!r} is already registered")
    SCORES[score.name] = score
    return score


def available_scores(
    names: list[str], has_eigenvalues: bool, has_autoencoder: bool, has_members: bool = False
) -> list[Score]:
    """The scores among `names` that a head (with or without eigenvalues; an ensemble's, with
    members) and an optional auto-encoder can give."""
    unknown = sorted(set(names) - set(SCORES))
    if unknown:
        raise ValueError(f"unknown OOD score(s) {unknown}; choose from {sorted(SCORES)}")
    return [
        SCORES[n]
        for n in names
        if (has_eigenvalues or not SCORES[n].needs_eigenvalues)
        and (has_members or not SCORES[n].needs_members)
        and (has_autoencoder or n != "autoencoder")
    ]


def quantile_threshold(train_scores: Tensor, q: float, keep_below: bool) -> float:
    """The threshold that keeps a fraction q of the (finite) reference scores.

    Args:
        train_scores: (N,) scores of the reference set (validation, or training).
        q: in [0, 1]; the q-quantile (keep-below) or (1 - q)-quantile (keep-above), linear
            interpolation as numpy's default.
        keep_below: the score's direction.

    Raises:
        ValueError: if q is outside [0, 1] or no training score is finite.
    """
    if not 0.0 <= q <= 1.0:
        raise ValueError(f"quantile {q} outside [0, 1]")
    finite = train_scores[torch.isfinite(train_scores)].double()
    if finite.numel() == 0:
        raise ValueError("no finite reference score to take a quantile of")
    return float(torch.quantile(finite, q if keep_below else 1.0 - q))


def keep_mask(scores: Tensor, threshold: float, keep_below: bool) -> Tensor:
    """(N,) bool: score < threshold (keep-below) or score > threshold (keep-above); NaN never."""
    return scores < threshold if keep_below else scores > threshold


def auroc(scores: Tensor, positive: Tensor, keep_below: bool) -> float:
    """Probability that a random positive (e.g. corrupted) sample looks LESS confident than a
    random negative (clean) one, ties counting 1/2 (`torchmetrics`' binary AUROC): 1 is a perfect
    detector, 0.5 chance, below 0.5 the score is inverted. NaN if either class is empty.
    Non-finite scores are dropped.

    Args:
        scores: (N,) a score's values.
        positive: (N,) bool, the samples to detect.
        keep_below: the score's direction (`Score.keep_below`): low values confident.
    """
    finite = torch.isfinite(scores)
    s, p = scores[finite].double(), positive[finite].bool()
    if not bool(p.any()) or bool(p.all()):
        return math.nan
    # torchmetrics reads predictions outside [0, 1] as logits and squashes them with a sigmoid,
    # which ties every score beyond about +-40 (DT values are -1e5 and lower): give it the
    # scores' dense ranks scaled into [0, 1] instead (the AUROC depends only on their order)
    _, order = torch.unique(s if keep_below else -s, return_inverse=True)
    unit = order.double() / max(int(order.max()), 1)
    return float(binary_auroc(unit, p.long()))


def spearman(x: Tensor, y: Tensor) -> float:
    """Spearman rank correlation of the finite pairs (ties get their mean rank; `torchmetrics`);
    NaN for fewer than 3 pairs or a constant input."""
    finite = torch.isfinite(x) & torch.isfinite(y)
    if int(finite.sum()) < 3:
        return math.nan
    x, y = x[finite].double(), y[finite].double()
    if bool((x == x[0]).all()) or bool((y == y[0]).all()):
        return math.nan
    return float(spearman_corrcoef(x, y))
