"""The matrix Fisher normaliser c(F), likelihood and sampling, through the Bingham belief A = -K(F).

Quaternions are scalar LAST. The density p(R; F) = exp(tr(F^T R)) / c(F) is taken w.r.t. the Haar
probability measure on SO(3) (package docstring, `rotlearn.fisher`); c(F) is the Bingham
normaliser Z(A) of `rotlearn.bingham` (Talbot inversion on a fixed node set, batched on any
device), evaluated at A's eigenvalues in closed form from F's proper singular values.
"""

from __future__ import annotations

import torch
from torch import Tensor

from rotlearn import bingham
from rotlearn.fisher.parameters import (
    _check_matrix,
    _check_range,
    _proper_svd,
    bingham_from_fisher,
)
from rotlearn.geometry import quat_to_rotmat
from rotlearn.geometry.autocast import float32_under_autocast, valued_as

__all__ = ["log_normalizer", "log_prob", "nll", "sample"]


def _log_normalizer_parts(F: Tensor, check: bool = True) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(U, V, s) of F's proper SVD and log N(lam), with log c(F) = s1 + s2 + s3 + log N(lam)
    (autograd-aware through s); `check`: s1 + s2 in range (a host sync), else taken at the
    bound (`rotlearn.bingham.log_normalizer`'s check=False).

    The eigenvalues of K(F) = -A are s1 + s2 + s3 (the largest) and s1 - s2 - s3, s2 - s1 - s3,
    s3 - s1 - s2: less the largest, the dispersions lam = -2 (s2 + s3, s1 + s3, s1 + s2) of
    Z(A) = e^{s1 + s2 + s3} N(lam), whose spread 2 (s1 + s2) is checked here."""
    U, s, V = _proper_svd(F)
    if check:
        _check_range(s)
    s1, s2, s3 = s.unbind(-1)
    lam = -2.0 * torch.stack((s1 + s2, s1 + s3, s2 + s3), -1)
    return U, V, s, bingham.log_normalizer(lam, check=False)


def _log_normalizer(F: Tensor, check: bool = True) -> Tensor:
    """log c(F) of finite F (`_log_normalizer_parts`)."""
    s, log_n = _log_normalizer_parts(F, check)[2:]
    return s.sum(-1) + log_n


@float32_under_autocast
def log_normalizer(F: Tensor) -> Tensor:
    """log c(F), c(F) = int_SO(3) exp(tr(F^T R)) dR over the Haar probability measure.

    Mohlin et al. (NeurIPS 2020) write c(F) as a 1-D integral of Bessel functions of the proper
    singular values; here it is the Bingham normaliser Z(A) = exp(-l1) N(lam) of A = -K(F)
    (`rotlearn.bingham.log_normalizer` of the four eigenvalues of K(F), package docstring).

    Args:
        F: (..., 3, 3) matrices, float32 or float64, s1 + s2 <= MAX_SINGULAR_SUM.

    Returns:
        (...,) log c in nats, in F's dtype (float32 under autocast); log c(0) = 0. Accuracy
        (measured against quadrature of the Bessel integral, package docstring): relative
        error of c at most 2.3e-12 in float64 for s1 <= 1e3, about eps * s1 beyond (1.2e-10 at
        1e5); in float32 at most 5e-7 (1 + s1). Differentiable once; the gradient is the mean
        rotation E[R] = U diag(m) V^T, finite everywhere and exact also where singular values
        repeat (F = 0, where it is 0; F a multiple of a rotation; s2 = -s3).

    Raises:
        ValueError: NaN/Inf in F, or s1 + s2 out of range; names the first batch index.
    """
    _check_matrix(F, "F", 3)
    return _log_normalizer(F)


@float32_under_autocast
def log_prob(F: Tensor, R: Tensor, check: bool = True) -> Tensor:
    """log p(R; F) = tr(F^T R) - log c(F) w.r.t. the Haar probability measure on SO(3).

    The same number as `rotlearn.bingham.log_prob(bingham_from_fisher(F), q)` for q a
    quaternion of R (tested), computed without the 4 x 4 eigen-decomposition.

    Args:
        F: (..., 3, 3) matrix Fisher parameters, as in `log_normalizer`.
        R: (..., 3, 3) rotation matrices, batch shape broadcast against F's; not projected onto
            SO(3).
        check: validate the values first (finite, s1 + s2 in range: host syncs). False, for a
            training loss's hot path (`rotlearn.losses.FisherNLLLoss`): dtypes and shapes only,
            no sync, as `rotlearn.bingham.log_prob`'s check=False.

    Returns:
        (...,) log densities; exp integrates to 1 against the Haar probability measure (for a
        Haar measure of total volume V, e.g. 8 pi^2 for sin(beta) d alpha d beta d gamma in
        Euler angles, subtract log V). Differentiable in F and R.
    """
    _check_matrix(F, "F", 3, values=check)
    _check_matrix(R, "R", 3, values=check)
    U, V, s, log_n = _log_normalizer_parts(F, check)
    # the fit s1 + s2 + s3 - tr(F^T R) >= 0, valued in float64 as tr(F^T (R0 - R)) at the mode
    # R0 = U V^T, orthogonal to float64 precision by one Newton-Schulz step (R0 is then exact
    # to second order in the SVD's error): in F's dtype the two terms, each of size s1, cancel
    # and float32 left ~1e-7 (s1 + s2) nats (the Bingham NLL's fit term is taken alike)
    fit = s.sum(-1) - (F * R).sum((-2, -1))
    with torch.no_grad():
        mode = U.double() @ V.double().mT
        mode = mode @ (
            1.5 * torch.eye(3, dtype=mode.dtype, device=mode.device) - 0.5 * mode.mT @ mode
        )
        exact = (F.double() * (mode - R.double())).sum((-2, -1)).clamp_min(0.0)
    return -valued_as(fit, exact) - log_n


def nll(F: Tensor, R: Tensor, check: bool = True) -> Tensor:
    """Negative log-likelihood log c(F) - tr(F^T R), the loss of Mohlin et al. (2020).

    Args and returns as `log_prob` (this is its negative), in nats.
    """
    return -log_prob(F, R, check=check)


@float32_under_autocast
def sample(F: Tensor, n: int, generator: torch.Generator | None = None) -> Tensor:
    """Draw n rotations from each matrix Fisher density p(R; F).

    `rotlearn.bingham.sample` of A = `bingham_from_fisher(F)` (Kent et al. 2013 rejection
    sampling, exact), mapped by `rotlearn.geometry.quat_to_rotmat`.

    Args:
        F: (..., 3, 3) matrices (finite).
        n: samples per matrix, >= 0.
        generator: random source (its device must be F's).

    Returns:
        (..., n, 3, 3) rotation matrices, F's dtype and device; no autograd.
    """
    _check_matrix(F, "F", 3)
    with torch.no_grad():
        q = bingham.sample(bingham_from_fisher(F), n, generator=generator)
        return quat_to_rotmat(q)
