"""The matrix Fisher parameter F and its Bingham matrix A = -K(F): the maps, the proper SVD, A's
eigenvalues in closed form, the mode.

Quaternions are scalar LAST, (x, y, z, w). The conventions (the density, the measure, the
identity tr(F^T R(q)) = q^T K(F) q) are those of the package docstring (`rotlearn.fisher`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from rotlearn.bingham import MAX_DISPERSION
from rotlearn.errors import batch_index
from rotlearn.geometry import special_orthogonalize
from rotlearn.geometry.autocast import float32_under_autocast
from rotlearn.geometry.shapes import require_shape

__all__ = [
    "MAX_SINGULAR_SUM",
    "bingham_from_fisher",
    "eigenvalues_from_fisher",
    "fisher_from_bingham",
    "mode",
    "proper_svd",
]

MAX_SINGULAR_SUM = MAX_DISPERSION / 2
"""Largest supported s1 + s2 (the two largest singular values of F): A's eigenvalue spread
l4 - l1 = 2 (s1 + s2) is then the Bingham normaliser's MAX_DISPERSION."""


# ----------------------------------------------------------------------------------- validation


def _raise_first(bad: Tensor, what: str) -> None:
    """Raise ValueError naming the first True of `bad` (batch-shaped), if any (one argmax)."""
    if bad.numel() and bool(bad.any()):
        flat = int(bad.reshape(-1).to(torch.uint8).argmax())
        raise ValueError(f"{what} at batch index {batch_index(flat, tuple(bad.shape))}")


def _check_matrix(M: Tensor, name: str, size: int, values: bool = True) -> None:
    """M is a floating (..., size, size) tensor; with `values`, without NaN or Inf (one host
    sync)."""
    if not M.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor, got {M.dtype}")
    require_shape(M, (size, size), name)
    if values:
        _raise_first(~torch.isfinite(M).flatten(-2).all(-1), f"{name} has NaN or Inf")


def _check_range(s: Tensor) -> None:
    """The proper singular values (..., 3) are within the normaliser's range."""
    _raise_first(
        s[..., 0] + s[..., 1] > MAX_SINGULAR_SUM,
        f"F's singular values s1 + s2 above MAX_SINGULAR_SUM = {MAX_SINGULAR_SUM:g} (unsupported)",
    )


# ------------------------------------------------------------------------------ F <-> A = -K(F)


@float32_under_autocast
def bingham_from_fisher(F: Tensor, *, check: bool = True) -> Tensor:
    """The Bingham matrix A = -K(F) of the matrix Fisher belief F (package docstring).

    exp(tr(F^T R(q))) = exp(-q^T A q) for every unit quaternion q, so `rotlearn.bingham` with
    this A is the same belief (log_prob, nll, sample, descriptors).

    Args:
        F: (..., 3, 3) matrices, float32 or float64.
        check: validate F (shape, dtype, NaN/Inf: one host synchronisation); the head passes
            False on its hot path, like `rotlearn.geometry.sym4_eigh_min`.

    Returns:
        (..., 4, 4) symmetric, traceless matrices in F's dtype, linear in F (exact: sums of
        three entries). Order (x, y, z, w), scalar last.
    """
    if check:
        _check_matrix(F, "F", 3)
    f11, f12, f13 = F[..., 0, 0], F[..., 0, 1], F[..., 0, 2]
    f21, f22, f23 = F[..., 1, 0], F[..., 1, 1], F[..., 1, 2]
    f31, f32, f33 = F[..., 2, 0], F[..., 2, 1], F[..., 2, 2]
    xy, xz, yz = f12 + f21, f13 + f31, f23 + f32
    xw, yw, zw = f32 - f23, f13 - f31, f21 - f12
    K = torch.stack(
        (
            torch.stack((f11 - f22 - f33, xy, xz, xw), -1),
            torch.stack((xy, f22 - f11 - f33, yz, yw), -1),
            torch.stack((xz, yz, f33 - f11 - f22, zw), -1),
            torch.stack((xw, yw, zw, f11 + f22 + f33), -1),
        ),
        -2,
    )
    return -K


@float32_under_autocast
def fisher_from_bingham(A: Tensor) -> Tensor:
    """The matrix Fisher parameter F of a Bingham matrix A: the inverse of `bingham_from_fisher`
    up to A's trace.

    K(F) spans exactly the traceless symmetric 4 x 4 matrices; A + c I defines the same density
    as A, so F = K^{-1}(-(A - tr(A)/4 I)), and `bingham_from_fisher(fisher_from_bingham(A))`
    is A minus its trace part. Every Bingham density on S^3 is a matrix Fisher density on
    SO(3).

    Args:
        A: (..., 4, 4) matrices (their symmetric part is used), float32 or float64.

    Returns:
        (..., 3, 3) in A's dtype, linear in A.
    """
    _check_matrix(A, "A", 4)
    K = -0.5 * (A + A.mT)
    half = 0.5 * K
    diagonal = K.diagonal(dim1=-2, dim2=-1)
    traceless = diagonal - diagonal.mean(-1, keepdim=True)  # the diagonal of K - tr(K)/4 I
    f11, f22, f33 = (0.5 * (traceless[..., :3] + traceless[..., 3:])).unbind(-1)
    xy, xz, xw = half[..., 0, 1], half[..., 0, 2], half[..., 0, 3]
    yz, yw, zw = half[..., 1, 2], half[..., 1, 3], half[..., 2, 3]
    return torch.stack(
        (
            torch.stack((f11, xy - zw, xz + yw), -1),
            torch.stack((xy + zw, f22, yz - xw), -1),
            torch.stack((xz - yw, yz + xw, f33), -1),
        ),
        -2,
    )


# ----------------------------------------------------------------------- singular values, mode


def _proper_svd(F: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(U, s, V) of validated F; gradients reach F only through torch.linalg.svd's S."""
    U, S, Vh = torch.linalg.svd(F)
    with torch.no_grad():  # det U, det V = +-1: constants of the backward
        flip_u, flip_v = torch.ones_like(S), torch.ones_like(S)
        flip_u[..., 2] = torch.linalg.det(U).sign()
        flip_v[..., 2] = torch.linalg.det(Vh).sign()
    return U * flip_u.unsqueeze(-2), S * (flip_u * flip_v), Vh.mT * flip_v.unsqueeze(-2)


@float32_under_autocast
def proper_svd(F: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The proper singular value decomposition F = U diag(s) V^T (Mohlin et al. 2020, sec. 3).

    Args:
        F: (..., 3, 3) matrices, float32 or float64.

    Returns:
        U (..., 3, 3) and V (..., 3, 3) rotations (det = +1), s (..., 3) with
        s1 >= s2 >= |s3| and sign(s3) = sign(det F) (from torch.linalg.svd, the third columns
        of U and V negated where their determinant is -1). Gradients: torch.linalg.svd's, so U
        and V have none where singular values repeat; s alone has U diag(g) V^T, finite
        everywhere (see `eigenvalues_from_fisher`).
    """
    _check_matrix(F, "F", 3)
    return _proper_svd(F)


@float32_under_autocast
def eigenvalues_from_fisher(F: Tensor, *, check: bool = True) -> Tensor:
    """The ascending eigenvalues of A = -K(F), in closed form from F's proper singular values.

    l1 = -(s1 + s2 + s3), l2 = -s1 + s2 + s3, l3 = s1 - s2 + s3, l4 = s1 + s2 - s3 (package
    docstring), so that the DT score (paper eq. 26) is -4 (s1 + s2 + s3) and the eigen-gap
    2 (s2 + s3), through their one definition in `rotlearn.bingham.descriptors`.

    Args:
        F: (..., 3, 3) matrices, float32 or float64.
        check: validate F, as in `bingham_from_fisher`.

    Returns:
        (..., 4) ascending, in F's dtype (float32 under autocast); within about eps * s1 of
        A's eigenvalues. Differentiable: the gradient reaches F through the singular values,
        U diag(g) V^T with the sign of s3 held fixed (from det U det V of the same SVD, so it
        matches the backward's singular vectors even where det F = 0). Where singular values
        repeat (F = 0, F a multiple of a rotation, s1 = s2, ...) it stays finite and is the
        exact gradient of any function of the eigenvalues that is smooth in F there (the
        normaliser, the likelihood: their gradient is equal on tied singular values); for a
        function with a kink there (e.g. the DT score at s2 = -s3) it is one of the one-sided
        gradients.
    """
    if check:
        _check_matrix(F, "F", 3)
    s1, s2, s3 = _proper_svd(F)[1].unbind(-1)
    return torch.stack((-(s1 + s2 + s3), s2 + s3 - s1, s1 - s2 + s3, s1 + s2 - s3), -1)


def mode(F: Tensor) -> Tensor:
    """The mode of the matrix Fisher belief: the rotation U V^T closest to F (SVD-9D, Levinson et
    al. 2020), `rotlearn.geometry.special_orthogonalize` itself.

    Args:
        F: (..., 3, 3) matrices, float32 or float64.

    Returns:
        (..., 3, 3) rotations in F's dtype (float32 under autocast); the backward is finite for
        repeated singular values. It equals quat_to_rotmat of `rotlearn.bingham.mode(A)` with
        A = `bingham_from_fisher(F)` wherever that mode is unique (s2 + s3 > 0).
    """
    _check_matrix(F, "F", 3)
    return special_orthogonalize(F)
