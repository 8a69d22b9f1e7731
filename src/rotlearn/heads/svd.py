"""SVD-9D: special orthogonalisation of a 3x3 matrix (Levinson et al., NeurIPS 2020)."""

from __future__ import annotations

from torch import Tensor

from rotlearn.geometry import special_orthogonalize
from rotlearn.geometry.autocast import float32_under_autocast
from rotlearn.heads.base import RotationHead, RotationPrediction, register_head

__all__ = ["SVD9DHead"]


@register_head
class SVD9DHead(RotationHead):
    """(..., 9) read row-major as a 3x3 matrix -> `rotlearn.geometry.special_orthogonalize`."""

    name = "svd9d"
    out_dim = 9

    @float32_under_autocast
    def forward(self, raw: Tensor) -> RotationPrediction:
        return RotationPrediction(R=special_orthogonalize(raw.unflatten(-1, (3, 3))), raw=raw)
