"""Floor 3: OOD scores, quantile thresholds and the test-time OOD evaluation (paper section V-A)."""

from rotlearn.ood.callback import OODEvaluation, pr_quantiles
from rotlearn.ood.evaluation import auroc, rank, rejection_row, spearman
from rotlearn.ood.scores import SCORES, Score, available_scores, keep_mask, quantile_threshold

__all__ = [
    "SCORES",
    "OODEvaluation",
    "Score",
    "auroc",
    "available_scores",
    "keep_mask",
    "pr_quantiles",
    "quantile_threshold",
    "rank",
    "rejection_row",
    "spearman",
]
