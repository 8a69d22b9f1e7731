"""Random rotations and directions, batched, drawn on any device from an optional generator."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from rotlearn.geometry.quaternion import quat_canonical, quat_normalize, quat_to_rotmat
from rotlearn.geometry.so3 import so3_exp

__all__ = [
    "random_quat",
    "random_rotmat",
    "random_rotmat_uniform_angle",
    "random_rotvec_uniform_angle",
    "random_unit_vectors",
]

Shape = Sequence[int] | torch.Size


def _randn(shape: Shape, generator, device, dtype) -> Tensor:
    if generator is not None and device is None:
        device = generator.device
    return torch.randn(tuple(shape), generator=generator, device=device, dtype=dtype)


def random_unit_vectors(
    shape: Shape,
    dim: int = 3,
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> Tensor:
    """Directions uniform on the sphere S^(dim-1) (normalised Gaussians).

    Args:
        shape: batch shape.
        dim: ambient dimension.
        generator: random source; its device is used when `device` is None.

    Returns:
        (*shape, dim) unit vectors.
    """
    v = _randn((*shape, dim), generator, device, dtype)
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)


def random_quat(
    shape: Shape,
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> Tensor:
    """Haar-uniform rotations as unit quaternions (x, y, z, w), canonical sign (w >= 0).

    Returns:
        (*shape, 4) unit quaternions.
    """
    q = _randn((*shape, 4), generator, device, dtype)
    return quat_canonical(quat_normalize(q))


def random_rotmat(
    shape: Shape,
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> Tensor:
    """Haar-uniform rotation matrices: (*shape, 3, 3)."""
    return quat_to_rotmat(random_quat(shape, generator=generator, device=device, dtype=dtype))


def random_rotvec_uniform_angle(
    shape: Shape,
    max_angle: float,
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> Tensor:
    """Rotation vectors with axis uniform on S^2 and angle ~ U[0, max_angle) (paper section VI-A).

    This is NOT Haar-uniform even for max_angle = pi: small angles are over-represented.

    Args:
        shape: batch shape.
        max_angle: phi_max in radians, in (0, pi].

    Returns:
        (*shape, 3) rotation vectors phi = angle * axis.
    """
    if not 0.0 < max_angle <= math.pi + 1e-12:
        raise ValueError(f"max_angle must lie in (0, pi] radians, got {max_angle}")
    axis = random_unit_vectors(shape, 3, generator=generator, device=device, dtype=dtype)
    u = torch.rand(tuple(shape), generator=generator, device=axis.device, dtype=axis.dtype)
    return axis * (u * max_angle).unsqueeze(-1)


def random_rotmat_uniform_angle(
    shape: Shape,
    max_angle: float,
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
) -> Tensor:
    """Exp of `random_rotvec_uniform_angle`: (*shape, 3, 3) rotation matrices."""
    phi = random_rotvec_uniform_angle(
        shape, max_angle, generator=generator, device=device, dtype=dtype
    )
    return so3_exp(phi)
