"""The exponential and logarithm maps of SO(3), stable at 0 and at pi.

Rotation vectors phi = angle * axis (radians). Exp(phi) is the rotation of `angle` about `axis`
(Sola et al. 2018 notation, as used in the paper's eq. 22 and section VI-A).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from rotlearn.geometry.autocast import float32_under_autocast
from rotlearn.geometry.quaternion import quat_canonical, quat_to_rotmat, rotmat_to_quat
from rotlearn.geometry.shapes import promoted, require_shape

__all__ = [
    "hat",
    "relative_rotation",
    "so3_exp",
    "so3_exp_quat",
    "so3_log",
    "so3_log_quat",
    "vee",
]


def hat(phi: Tensor) -> Tensor:
    """Skew-symmetric matrices [phi]_x with [phi]_x v = phi x v.

    Args:
        phi: (..., 3) vectors.

    Returns:
        (..., 3, 3) skew-symmetric matrices.
    """
    require_shape(phi, (3,), "phi")
    x, y, z = phi.unbind(-1)
    zero = torch.zeros_like(x)
    rows = (zero, -z, y, z, zero, -x, -y, x, zero)
    return torch.stack(rows, dim=-1).unflatten(-1, (3, 3))


def vee(S: Tensor) -> Tensor:
    """Inverse of `hat` on the skew-symmetric part: (..., 3, 3) -> (..., 3)."""
    require_shape(S, (3, 3), "S")
    return 0.5 * torch.stack(
        (S[..., 2, 1] - S[..., 1, 2], S[..., 0, 2] - S[..., 2, 0], S[..., 1, 0] - S[..., 0, 1]),
        dim=-1,
    )


def so3_exp_quat(phi: Tensor) -> Tensor:
    """Unit quaternions of rotation vectors: q = (sin(t/2) phi / t, cos(t/2)), t = |phi|.

    Smooth everywhere, including phi = 0 (sinc form, finite gradient).

    Args:
        phi: (..., 3) rotation vectors, radians.

    Returns:
        (..., 4) unit quaternions (x, y, z, w). w >= 0 for |phi| <= pi.
    """
    require_shape(phi, (3,), "phi")
    angle = torch.linalg.vector_norm(phi, dim=-1, keepdim=True)
    half = 0.5 * angle
    xyz = 0.5 * torch.sinc(half / math.pi) * phi
    return torch.cat((xyz, torch.cos(half)), dim=-1)


def so3_exp(phi: Tensor) -> Tensor:
    """Exp: rotation vectors -> rotation matrices (Rodrigues), stable at 0 and at pi.

    Args:
        phi: (..., 3) rotation vectors, radians.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    require_shape(phi, (3,), "phi")
    return quat_to_rotmat(so3_exp_quat(phi))


def so3_log_quat(q: Tensor) -> Tensor:
    """Log of unit quaternions: rotation vectors with angle in [0, pi].

    Args:
        q: (..., 4) unit quaternions (x, y, z, w); the sign does not matter.

    Returns:
        (..., 3) rotation vectors phi with |phi| <= pi and Exp(phi) = R(q).
    """
    require_shape(q, (4,), "q")
    q = quat_canonical(q)
    xyz, w = q[..., :3], q[..., 3:]
    n = torch.linalg.vector_norm(xyz, dim=-1, keepdim=True)
    small = n < 1e-4
    n_safe = torch.where(small, torch.ones_like(n), n)
    w_safe = torch.where(small, w, torch.ones_like(w))
    # 2 atan2(n, w) / n, and its series 2/w (1 - n^2 / (3 w^2)) where n -> 0 (w ~ 1 there).
    scale = torch.where(
        small,
        2.0 / w_safe * (1.0 - n * n / (3.0 * w_safe * w_safe)),
        2.0 * torch.atan2(n_safe, w) / n_safe,
    )
    return scale * xyz


def so3_log(R: Tensor) -> Tensor:
    """Log: rotation matrices -> rotation vectors, stable at 0 and at pi.

    Args:
        R: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) rotation vectors phi with |phi| in [0, pi] and so3_exp(phi) = R. At exactly pi
        the axis sign is the one `quat_canonical` picks.
    """
    require_shape(R, (3, 3), "R")
    return so3_log_quat(rotmat_to_quat(R))


@float32_under_autocast
def relative_rotation(R_w1: Tensor, R_w2: Tensor) -> Tensor:
    """The rotation C_21 = R_w2^T R_w1 from frame 1 to frame 2 (paper section VI-C).

    With camera-to-world orientations R_wi (p_w = R_wi p_i + t_wi, as in KITTI's poses files),
    C_21 is the rotation part of T_21 = T_w2^-1 T_w1: it maps a direction in camera-1
    coordinates to camera-2 coordinates, d_2 = C_21 d_1.

    Args:
        R_w1, R_w2: (..., 3, 3) camera-to-world rotations of the first and second frame.

    Returns:
        (..., 3, 3) C_21, in the inputs' (promoted) dtype (float32 under autocast).
    """
    require_shape(R_w1, (3, 3), "R_w1")
    require_shape(R_w2, (3, 3), "R_w2")
    R_w1, R_w2 = promoted(R_w1, R_w2)
    return R_w2.transpose(-1, -2) @ R_w1
