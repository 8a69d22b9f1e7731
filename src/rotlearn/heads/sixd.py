"""The continuous 6D representation of Zhou et al. (CVPR 2019): Gram-Schmidt on two 3-vectors."""

from __future__ import annotations

import torch
from torch import Tensor

from rotlearn.heads.base import RotationHead, RotationPrediction, register_head

__all__ = ["SixDHead", "sixd_to_rotmat"]


def _normalize(v: Tensor, eps: float = 1e-12) -> Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(eps)


def sixd_to_rotmat(v: Tensor) -> Tensor:
    """Rotation matrices from 6D vectors, the vectors giving the COLUMNS.

    x = normalize(v[0:3]); z = normalize(x cross v[3:6]); y = z cross x; R = [x y z].

    Args:
        v: (..., 6) vectors; the two halves must not be parallel.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    x = _normalize(v[..., 0:3])
    z = _normalize(torch.linalg.cross(x, v[..., 3:6]))
    y = torch.linalg.cross(z, x)
    return torch.stack((x, y, z), dim=-1)


@register_head
class SixDHead(RotationHead):
    """(..., 6) -> rotation by Gram-Schmidt (`sixd_to_rotmat`)."""

    name = "sixd"
    out_dim = 6

    def forward(self, raw: Tensor) -> RotationPrediction:
        return RotationPrediction(R=sixd_to_rotmat(raw), raw=raw)
