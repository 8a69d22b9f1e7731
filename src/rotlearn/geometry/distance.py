"""Distances between rotations (paper eqs. 20-22). One angle function serves the whole project."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from rotlearn.geometry.autocast import float32_under_autocast
from rotlearn.geometry.shapes import promoted, require_shape

__all__ = ["angle", "angle_deg", "chordal_distance", "chordal_distance_sq", "quat_chordal_distance"]

_TWO_SQRT2 = 2.0 * math.sqrt(2.0)


@float32_under_autocast
def angle(R1: Tensor, R2: Tensor) -> Tensor:
    """Geodesic angle |Log(R1^T R2)| between rotations (paper eq. 22), in radians, in [0, pi].

    Computed as 2 atan2(sin(t/2), cos(t/2)) with both halves written as norms of expressions
    linear in R1^T R2 (sin(t/2) = |R1 - R2|_F / (2 sqrt 2), cos(t/2) = |w| of the relative
    quaternion, read off 4 w q = (r21 - r12, r02 - r20, r10 - r01, 1 + tr)). So there is no
    acos: the value is accurate near 0 and 180 degrees, and the gradient is finite everywhere
    (zero at exactly 0 degrees, and where R1^T R2 is exactly a half-turn in floating point, where
    the angle has a kink; a half-turn computed with rounding gets a subgradient of norm <= 1).

    Args:
        R1: (..., 3, 3) rotation matrices.
        R2: (..., 3, 3) rotation matrices, broadcast against R1.

    Returns:
        (...) angles in radians, in the inputs' (promoted) dtype and on their device; float32 under
        autocast (a bfloat16 R1^T R2 would put ~0.5 degree of rounding into small angles).
    """
    require_shape(R1, (3, 3), "R1")
    require_shape(R2, (3, 3), "R2")
    R1, R2 = promoted(R1, R2)
    sin_half = torch.linalg.matrix_norm(R1 - R2) / _TWO_SQRT2
    rel = R1.transpose(-1, -2) @ R2
    trace = torch.diagonal(rel, dim1=-2, dim2=-1).sum(-1)
    four_w_q = torch.stack(
        (
            rel[..., 2, 1] - rel[..., 1, 2],
            rel[..., 0, 2] - rel[..., 2, 0],
            rel[..., 1, 0] - rel[..., 0, 1],
            1.0 + trace,
        ),
        dim=-1,
    )
    cos_half = torch.linalg.vector_norm(four_w_q, dim=-1) / 4.0
    return 2.0 * torch.atan2(sin_half, cos_half)


def angle_deg(R1: Tensor, R2: Tensor) -> Tensor:
    """`angle` in degrees: (..., 3, 3), (..., 3, 3) -> (...)."""
    return torch.rad2deg(angle(R1, R2))


def chordal_distance_sq(R1: Tensor, R2: Tensor) -> Tensor:
    """Squared chordal distance |R1 - R2|_F^2 = 8 sin^2(t/2) (paper eq. 17, the training loss).

    Args:
        R1: (..., 3, 3) rotation matrices.
        R2: (..., 3, 3) rotation matrices, broadcast against R1.

    Returns:
        (...) squared distances, in [0, 8].
    """
    require_shape(R1, (3, 3), "R1")
    require_shape(R2, (3, 3), "R2")
    return (R1 - R2).square().sum((-1, -2))


def chordal_distance(R1: Tensor, R2: Tensor) -> Tensor:
    """Chordal distance |R1 - R2|_F (paper eq. 21): (..., 3, 3), (..., 3, 3) -> (...)."""
    require_shape(R1, (3, 3), "R1")
    require_shape(R2, (3, 3), "R2")
    return torch.linalg.matrix_norm(R1 - R2)


def quat_chordal_distance(q1: Tensor, q2: Tensor) -> Tensor:
    """Sign-invariant quaternion distance min(|q1 - q2|, |q1 + q2|) (paper eq. 20).

    Args:
        q1: (..., 4) unit quaternions (x, y, z, w).
        q2: (..., 4) unit quaternions (x, y, z, w), broadcast against q1.

    Returns:
        (...) distances d in [0, sqrt 2]; |R(q1) - R(q2)|_F^2 = 2 d^2 (4 - d^2).
    """
    require_shape(q1, (4,), "q1")
    require_shape(q2, (4,), "q2")
    minus = torch.linalg.vector_norm(q1 - q2, dim=-1)
    plus = torch.linalg.vector_norm(q1 + q2, dim=-1)
    return torch.minimum(minus, plus)
