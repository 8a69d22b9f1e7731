"""The continuous 6D representation of Zhou et al. (CVPR 2019): Gram-Schmidt on two 3-vectors."""

from __future__ import annotations

import torch
from torch import Tensor

from rotlearn.geometry.autocast import float32_under_autocast
from rotlearn.geometry.shapes import require_shape

__all__ = ["sixd_to_rotmat"]


def _normalize(v: Tensor, eps: float = 1e-12) -> Tensor:
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(eps)


@float32_under_autocast
def sixd_to_rotmat(v: Tensor) -> Tensor:
    """Rotation matrices from 6D vectors, the vectors giving the COLUMNS.

    x = normalize(v[0:3]); z = normalize(x cross v[3:6]); y = z cross x; R = [x y z].

    Args:
        v: (..., 6) vectors, any batch shape, float32 or float64; the two halves must not be
            parallel.

    Returns:
        (..., 3, 3) rotation matrices in v's dtype; under autocast (CPU or CUDA) float32 (a
        rotation in bfloat16 is orthogonal only to ~4e-3).
    """
    require_shape(v, (6,), "v")
    x = _normalize(v[..., 0:3])
    z = _normalize(torch.linalg.cross(x, v[..., 3:6]))
    y = torch.linalg.cross(z, x)
    return torch.stack((x, y, z), dim=-1)
