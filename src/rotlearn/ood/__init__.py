"""Floor 3: OOD scores, quantile thresholds and the test-time OOD evaluation (paper section V-A):
pure functions (`evaluation`), writers (`report`), the datamodule protocol they read (`source`)
and the thin `OODEvaluation` callback that wires them (imported on first use: it is a Lightning
callback, and the report writers do without Lightning, e.g. `rotlearn-report`)."""

from typing import TYPE_CHECKING, Any

from rotlearn.ood.evaluation import (
    auroc,
    calibrated_threshold,
    evaluate,
    mixed_set,
    pr_quantiles,
    precision_recall_curve,
    rank,
    rejection_row,
    rejection_table,
    score_sets,
    spearman,
    table_quantile,
)
from rotlearn.ood.scores import SCORES, Score, available_scores, keep_mask, quantile_threshold
from rotlearn.ood.source import OODDataSource

if TYPE_CHECKING:
    from rotlearn.ood.callback import OODEvaluation

__all__ = [
    "SCORES",
    "OODDataSource",
    "OODEvaluation",
    "Score",
    "auroc",
    "available_scores",
    "calibrated_threshold",
    "evaluate",
    "keep_mask",
    "mixed_set",
    "pr_quantiles",
    "precision_recall_curve",
    "quantile_threshold",
    "rank",
    "rejection_row",
    "rejection_table",
    "score_sets",
    "spearman",
    "table_quantile",
]


def __getattr__(name: str) -> Any:  # PEP 562
    if name == "OODEvaluation":
        from rotlearn.ood.callback import OODEvaluation

        return OODEvaluation
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
