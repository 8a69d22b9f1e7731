"""torchmetrics metrics over whole epochs (they sync across processes under DDP)."""

from __future__ import annotations

import torch
from torch import Tensor

from rotlearn.extras import require

require("train", "rotlearn.metrics")

from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat

from rotlearn.geometry import angle_deg

__all__ = ["AngularError"]


class AngularError(Metric):
    """Geodesic rotation error in degrees, summarised over every sample seen since the last reset.

    `update(R_pred, R_true)` takes (..., 3, 3) batches; `compute()` returns
    {"err_mean", "err_median", "err_p10", "err_p90"} as 0-dim tensors (percentiles interpolated).
    """

    is_differentiable = False
    higher_is_better = False
    full_state_update = False

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.add_state("errors", default=[], dist_reduce_fx="cat")

    def update(self, R_pred: Tensor, R_true: Tensor) -> None:
        self.errors.append(angle_deg(R_pred.detach(), R_true).flatten().to(torch.float64))

    def values(self) -> Tensor:
        """(n,) every error seen since the last reset, in degrees (float64)."""
        return dim_zero_cat(self.errors)

    def compute(self) -> dict[str, Tensor]:
        errors = self.values()
        p10, median, p90 = torch.quantile(errors, errors.new_tensor([0.1, 0.5, 0.9]))
        return {"err_mean": errors.mean(), "err_median": median, "err_p10": p10, "err_p90": p90}
