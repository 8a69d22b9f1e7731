"""Floor 3: the test-time OOD evaluation (paper section V-A): pure functions (`evaluation`), the
records it writes (`records`), the datamodule protocol they read (`source`) and the thin
`OODEvaluation` callback that wires them (imported on first use: it is a Lightning callback, and
the records do without Lightning, e.g. `rotlearn-report`). The scores themselves, their quantile
thresholds and rank statistics live below, in `rotlearn.scores`; `rotlearn.ood` and
`rotlearn.lit` never import each other."""

from typing import TYPE_CHECKING, Any

from rotlearn.ood.evaluation import (
    REFERENCE_SETS,
    calibrated_threshold,
    evaluate,
    mixed_set,
    pr_quantiles,
    precision_recall_curve,
    reference_set,
    rejection_row,
    rejection_table,
    score_sets,
    table_quantile,
)
from rotlearn.ood.source import OODDataSource

if TYPE_CHECKING:
    from rotlearn.ood.callback import OODEvaluation

__all__ = [
    "REFERENCE_SETS",
    "OODDataSource",
    "OODEvaluation",
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


def __getattr__(name: str) -> Any:  # PEP 562
    if name == "OODEvaluation":
        from rotlearn.ood.callback import OODEvaluation

        return OODEvaluation
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
