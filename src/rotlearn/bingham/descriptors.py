"""Descriptors of the Bingham belief A (paper III-C, eq. 26): mode, dispersion, DT, eigen-gap.

Quaternions are scalar LAST, (x, y, z, w). The conventions (the sign of the exponent, the order
of the coefficients, the measure) are those of the package docstring (`rotlearn.bingham`). Each
quantity of a prediction's eigenvalues is DEFINED here once (`*_from_eigenvalues`);
`rotlearn.heads.RotationPrediction` and the OOD scores read them from these functions.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from rotlearn.errors import batch_index
from rotlearn.geometry import linalg, sym4_eigh_min
from rotlearn.geometry.shapes import require_shape

__all__ = [
    "LOG_AREA_S3",
    "MAX_DISPERSION",
    "bingham_parameters",
    "dispersion",
    "dispersion_from_eigenvalues",
    "dt_from_eigenvalues",
    "dt_score",
    "eigengap",
    "eigengap_from_eigenvalues",
    "eigenvalues",
    "eigh",
    "mode",
]

MAX_DISPERSION = 1e8
"""Largest supported |dispersion coefficient| (eigenvalue spread l4 - l1 of A).

A belief whose typical error is theta radians has |lam| ~ 2 / theta^2: 6.6e3 at 1 degree, 6.6e6
at 0.03 degrees (the A head's test error on the KITTI-format world at the paper's scale), 1e8 at
0.008 degrees. The normaliser and its moments are verified up to 1e8 in both dtypes, and the NLL's
fit term is taken without cancellation (`rotlearn.bingham.log_prob`), so a float32 NLL stays
within 1e-3 nats of the float64 one of the same A across the range (tested; 3e-5 measured)."""

LOG_AREA_S3 = math.log(2.0 * math.pi**2)
"""log |S^3|: subtract from `log_prob` for a density w.r.t. the surface measure."""


# ------------------------------------------------------------------------ eigen-decomposition


def _symmetric(A: Tensor) -> Tensor:
    """The symmetric part (A + A^T) / 2 (it defines the same density as A), in float32 where A
    is of a lower precision (the solvers take float32 and float64)."""
    if A.dtype not in (torch.float32, torch.float64):
        A = A.float()
    return 0.5 * (A + A.mT)


def _decompose(A: Tensor) -> tuple[Tensor, Tensor]:
    """Ascending eigenvalues (..., 4) and the mode (..., 4) of A, in A's dtype, from the A
    head's solver (`rotlearn.geometry.sym4_eigh_min`): finite gradients at repeated eigenvalues."""
    ev, q = sym4_eigh_min(_symmetric(A), check=False)
    return ev.to(A.dtype), q.to(A.dtype)


def eigenvalues(A: Tensor) -> Tensor:
    """Ascending eigenvalues (..., 4) of the symmetric part of A (..., 4, 4), in A's dtype; the
    gradient v_i v_i^T is well defined at repeated eigenvalues."""
    return _decompose(A)[0]


def eigh(A: Tensor) -> tuple[Tensor, Tensor]:
    """All eigenvalues (..., 4), ascending, and unit eigenvectors as columns (..., 4, 4) of the
    symmetric part of A, in A's dtype (`torch.linalg.eigh`; used where every direction is
    needed: `bingham_parameters`, sampling)."""
    ev, V = linalg.eigh(_symmetric(A))
    return ev.to(A.dtype), V.to(A.dtype)


# ----------------------------------------------------------------------------------- validation


def _raise_first(bad: Tensor, what: str) -> None:
    """Raise ValueError naming the first True of `bad` (batch-shaped), if any (one argmax)."""
    if bad.numel() and bool(bad.any()):
        flat = int(bad.reshape(-1).to(torch.uint8).argmax())
        raise ValueError(f"{what} at batch index {batch_index(flat, tuple(bad.shape))}")


def _float_dtype(t: Tensor, name: str) -> None:
    if not t.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor, got {t.dtype}")


def _check_A(A: Tensor, values: bool = True) -> None:
    """A's dtype and shape; with `values`, also its entries (finite: one host sync)."""
    _float_dtype(A, "A")
    require_shape(A, (4, 4), "A")
    if values:
        _raise_first(~torch.isfinite(A).flatten(-2).all(-1), "A has NaN or Inf")


def _check_q(q: Tensor, values: bool = True) -> None:
    """q's dtype and shape (..., 4); with `values`, also its entries (finite: one host sync)."""
    _float_dtype(q, "q")
    require_shape(q, (4,), "q")
    if values:
        _raise_first(~torch.isfinite(q).all(-1), "q has NaN or Inf")


def _check_lam(lam: Tensor) -> None:
    _float_dtype(lam, "lam")
    if lam.dim() < 1 or lam.shape[-1] not in (3, 4):
        raise ValueError(f"lam must have shape (..., 3) or (..., 4), got {tuple(lam.shape)}")
    finite = torch.isfinite(lam).all(-1)
    if lam.shape[-1] == 3:
        ok = finite & (lam <= 0).all(-1) & (lam >= -MAX_DISPERSION).all(-1)
    else:
        ok = finite & (lam.amax(-1) - lam.amin(-1) <= MAX_DISPERSION)
    if bool(ok.all()):
        return
    _raise_first(~finite, "lam has NaN or Inf")
    if lam.shape[-1] == 3:
        _raise_first((lam > 0).any(-1), "dispersion coefficients must be <= 0; lam has one > 0")
        _raise_first(
            (lam < -MAX_DISPERSION).any(-1),
            f"dispersion coefficient below -MAX_DISPERSION = {-MAX_DISPERSION:g} (unsupported)",
        )
    _raise_first(
        lam.amax(-1) - lam.amin(-1) > MAX_DISPERSION,
        f"coefficient spread max(lam) - min(lam) above MAX_DISPERSION = {MAX_DISPERSION:g}",
    )


def _check_spread(eigenvalues: Tensor) -> None:
    spread = eigenvalues[..., 3] - eigenvalues[..., 0]
    _raise_first(
        spread > MAX_DISPERSION,
        f"eigenvalue spread l4 - l1 of A above MAX_DISPERSION = {MAX_DISPERSION:g} (unsupported)",
    )


# ----------------------------------------------------------------------- descriptors of A (eq. 26)


def mode(A: Tensor) -> Tensor:
    """The mode of the belief: A's minimum eigenvector (paper eq. 11; d4 in eq. 15).

    Args:
        A: (..., 4, 4) symmetric matrices.

    Returns:
        (..., 4) unit quaternions (x, y, z, w) with canonical sign (w >= 0): the A head's
        quaternion, from the same solver, so the gradient is finite where l1 == l2 (eq. 9 with
        the gaps clamped, `rotlearn.geometry.sym4_eigh_min`).
    """
    _check_A(A)
    return _decompose(A)[1]


def dispersion_from_eigenvalues(eigenvalues: Tensor) -> Tensor:
    """Dispersion coefficients (l1 - l4, l1 - l3, l1 - l2), (..., 3) ascending and <= 0, from the
    ascending eigenvalues (..., 4) of A (as the A head gives them). THE definition that every
    dispersion in rotlearn comes from."""
    return eigenvalues[..., :1] - eigenvalues[..., [3, 2, 1]]


def dt_from_eigenvalues(eigenvalues: Tensor) -> Tensor:
    """The DT score tr(Lambda) = 3 l1 - l2 - l3 - l4 <= 0 (paper eq. 26), (...,), from the
    ascending eigenvalues (..., 4): the sum of the dispersion coefficients. Lower = more
    confident. THE definition that every DT score in rotlearn comes from."""
    return dispersion_from_eigenvalues(eigenvalues).sum(-1)


def eigengap_from_eigenvalues(eigenvalues: Tensor) -> Tensor:
    """The first eigen-gap l2 - l1 >= 0, (...,), from the ascending eigenvalues (..., 4): the gap
    that makes the mode unique (= -lam_3). THE definition of the eigen-gap in rotlearn."""
    return eigenvalues[..., 1] - eigenvalues[..., 0]


def dispersion(A: Tensor) -> Tensor:
    """Dispersion coefficients (l1 - l4, l1 - l3, l1 - l2) of the belief A (paper III-C).

    Args:
        A: (..., 4, 4) symmetric matrices.

    Returns:
        (..., 3) ascending coefficients lam_1 <= lam_2 <= lam_3 <= 0, attached to the
        eigenvectors (v4, v3, v2); more negative = more concentrated. Invariant to A -> A + cI.
    """
    _check_A(A)
    return dispersion_from_eigenvalues(eigenvalues(A))


def bingham_parameters(A: Tensor) -> tuple[Tensor, Tensor]:
    """The paper's (D, Lambda) of eq. (15): D Lambda D^T = -A + l1 I.

    Args:
        A: (..., 4, 4) symmetric matrices.

    Returns:
        D (..., 4, 4) orthogonal, columns (d1, d2, d3, d4) = (v4, v3, v2, v1) with d4 the mode
        (sign as returned by the solver), and lam (..., 3) = `dispersion(A)`, so that
        Lambda = diag(lam_1, lam_2, lam_3, 0).
    """
    _check_A(A)
    ev, V = eigh(A)
    return V[..., [3, 2, 1, 0]], dispersion_from_eigenvalues(ev)


def dt_score(A: Tensor) -> Tensor:
    """Dispersion-thresholding score tr(Lambda) = 3 l1 - l2 - l3 - l4 (paper eq. 26).

    Args:
        A: (..., 4, 4) symmetric matrices.

    Returns:
        (...,) the sum of the dispersion coefficients, <= 0; MORE NEGATIVE = MORE CONFIDENT
        (the paper keeps the samples below a quantile of the training scores). Invariant to
        A -> A + cI.
    """
    _check_A(A)
    return dt_from_eigenvalues(eigenvalues(A))


def eigengap(A: Tensor) -> Tensor:
    """l2 - l1 >= 0: the gap that makes the mode well defined (= -lam_3, the weakest dispersion).

    Args:
        A: (..., 4, 4) symmetric matrices.

    Returns:
        (...,) the gap between A's two smallest eigenvalues; 0 means the mode is not unique.
    """
    _check_A(A)
    return eigengap_from_eigenvalues(eigenvalues(A))
