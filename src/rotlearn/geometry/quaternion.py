"""Unit quaternions, scalar LAST: q = (x, y, z, w), Hamilton product, active rotations.

q and -q represent the same rotation. Every function takes any leading batch shape, works in
float32 and float64 on any device, and returns tensors in its input's dtype and device.
"""

from __future__ import annotations

import torch
from torch import Tensor

from rotlearn.geometry.shapes import require_shape

__all__ = [
    "quat_canonical",
    "quat_inverse",
    "quat_multiply",
    "quat_normalize",
    "quat_to_rotmat",
    "rotmat_to_quat",
]


def quat_normalize(q: Tensor, eps: float = 1e-12) -> Tensor:
    """Scale quaternions to unit length.

    Args:
        q: (..., 4) quaternions (x, y, z, w), nonzero.
        eps: lower bound on the norm, so that a zero vector gives zeros rather than NaN.

    Returns:
        (..., 4) unit quaternions.
    """
    require_shape(q, (4,), "q")
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True).clamp_min(eps)


def quat_canonical(q: Tensor) -> Tensor:
    """Pick the representative of {q, -q} with w > 0.

    Ties (w == 0) are broken deterministically: the first nonzero component in the order
    w, x, y, z is made positive. The map is a sign flip, so gradients pass through unchanged.

    Args:
        q: (..., 4) quaternions (x, y, z, w).

    Returns:
        (..., 4) the same rotations with the canonical sign.
    """
    require_shape(q, (4,), "q")
    x, y, z, w = q.unbind(-1)
    sign = torch.sign(w)
    for part in (x, y, z):
        sign = torch.where(sign == 0, torch.sign(part), sign)
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    return q * sign.unsqueeze(-1)


def quat_multiply(p: Tensor, q: Tensor) -> Tensor:
    """Hamilton product p * q (apply q first, then p, as rotations).

    Args:
        p: (..., 4) quaternions (x, y, z, w).
        q: (..., 4) quaternions (x, y, z, w); broadcast against p.

    Returns:
        (..., 4) the product, with R(p * q) = R(p) @ R(q).
    """
    require_shape(p, (4,), "p")
    require_shape(q, (4,), "q")
    px, py, pz, pw = p.unbind(-1)
    qx, qy, qz, qw = q.unbind(-1)
    return torch.stack(
        (
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
            pw * qw - px * qx - py * qy - pz * qz,
        ),
        dim=-1,
    )


def quat_inverse(q: Tensor) -> Tensor:
    """Inverse q^-1 = conj(q) / |q|^2 (the conjugate for unit quaternions).

    Args:
        q: (..., 4) nonzero quaternions (x, y, z, w).

    Returns:
        (..., 4) quaternions with q * q^-1 = (0, 0, 0, 1).
    """
    require_shape(q, (4,), "q")
    conj = q * q.new_tensor([-1.0, -1.0, -1.0, 1.0])
    return conj / (q * q).sum(-1, keepdim=True)


def quat_to_rotmat(q: Tensor) -> Tensor:
    """Rotation matrices of quaternions (paper section IV-A, R(q)).

    Args:
        q: (..., 4) nonzero quaternions, scalar last (x, y, z, w). q and -q give the same
            matrix. Non-unit quaternions are treated as their normalisation (the formula divides
            by |q|^2, so a zero quaternion gives NaN; it is not checked: that would need the
            values on the host).

    Returns:
        (..., 3, 3) rotation matrices R with R v = q * v * q^-1 (active rotation).
    """
    require_shape(q, (4,), "q")
    x, y, z, w = q.unbind(-1)
    s = 2.0 / (q * q).sum(-1)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    rows = (
        1.0 - yy - zz, xy - wz, xz + wy,
        xy + wz, 1.0 - xx - zz, yz - wx,
        xz - wy, yz + wx, 1.0 - xx - yy,
    )  # fmt: skip
    return torch.stack(rows, dim=-1).unflatten(-1, (3, 3))


def rotmat_to_quat(R: Tensor) -> Tensor:
    """Unit quaternions of rotation matrices, stable at every angle (0 and 180 degrees included).

    Uses the symmetric matrix K = 4 q q^T, whose entries are linear in R: the row of K with the
    largest diagonal entry (always >= 1) is parallel to q, so normalising it gives q without a
    square root of a small number. The result has w >= 0 (see `quat_canonical`).

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 4) unit quaternions (x, y, z, w) with R = quat_to_rotmat(q).
    """
    require_shape(R, (3, 3), "R")
    r = R.flatten(-2)
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r.unbind(-1)
    k = torch.stack(
        (
            1.0 + r00 - r11 - r22, r01 + r10, r02 + r20, r21 - r12,
            r01 + r10, 1.0 - r00 + r11 - r22, r12 + r21, r02 - r20,
            r02 + r20, r12 + r21, 1.0 - r00 - r11 + r22, r10 - r01,
            r21 - r12, r02 - r20, r10 - r01, 1.0 + r00 + r11 + r22,
        ),
        dim=-1,
    ).unflatten(-1, (4, 4))  # fmt: skip
    best = torch.diagonal(k, dim1=-2, dim2=-1).argmax(-1, keepdim=True)
    row = torch.take_along_dim(k, best.unsqueeze(-1), dim=-2).squeeze(-2)
    return quat_canonical(quat_normalize(row))
