"""The continuous 6D representation of Zhou et al. (CVPR 2019): Gram-Schmidt on two 3-vectors."""

from __future__ import annotations

from torch import Tensor

from rotlearn.geometry import sixd_to_rotmat
from rotlearn.geometry.autocast import float32_under_autocast
from rotlearn.heads.base import RotationHead, RotationPrediction, register_head

__all__ = ["SixDHead"]


@register_head
class SixDHead(RotationHead):
    """(..., 6) -> rotation by Gram-Schmidt (`rotlearn.geometry.sixd_to_rotmat`)."""

    name = "sixd"
    out_dim = 6

    @float32_under_autocast
    def forward(self, raw: Tensor) -> RotationPrediction:
        return RotationPrediction(R=sixd_to_rotmat(raw), raw=raw)
