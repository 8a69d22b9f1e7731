"""The paper's representation: a symmetric 4x4 matrix A whose minimum eigenvector is the rotation.

Paper section III: A(theta) fills a symmetric matrix from 10 numbers (eq. 8); the rotation is the
unit quaternion minimising q^T A q (eq. 6), i.e. the eigenvector of A's smallest eigenvalue
(eq. 11), with sign fixed so that w >= 0. The smooth global section is g(q) = I - q q^T (eq. 12).
"""

from __future__ import annotations

import warnings

import torch
from torch import Tensor

from rotlearn.errors import ConfigError
from rotlearn.geometry import quat_to_rotmat, sym4_eigh_min
from rotlearn.geometry.eigen4 import METHODS
from rotlearn.heads.base import RotationHead, RotationPrediction, register_head

__all__ = ["SOLVERS", "AHead", "a_from_quat", "a_from_vec", "a_min_eigvec", "vec_from_a"]

SOLVERS = METHODS  # rep.solver: the `method` of rotlearn.geometry.sym4_eigh_min
DEPRECATED_SOLVERS = {"fast": "auto"}  # names that configs saved by earlier versions hold

# Row-major upper triangle of a 4x4 matrix: a00 a01 a02 a03 a11 a12 a13 a22 a23 a33 (eq. 8).
_TRIU_ROWS, _TRIU_COLS = torch.triu_indices(4, 4)
# For each of the 16 entries (row-major), its index in the 10-vector (the mirror for i > j).
_FULL_FROM_TRIU = torch.empty(16, dtype=torch.long)
_FULL_FROM_TRIU[_TRIU_ROWS * 4 + _TRIU_COLS] = torch.arange(10)
_FULL_FROM_TRIU[_TRIU_COLS * 4 + _TRIU_ROWS] = torch.arange(10)


def a_from_vec(theta: Tensor) -> Tensor:
    """Symmetric matrices from their upper triangles (paper eq. 8).

    Args:
        theta: (..., 10) entries [a00, a01, a02, a03, a11, a12, a13, a22, a23, a33].

    Returns:
        (..., 4, 4) symmetric matrices A, rows and columns in quaternion order (x, y, z, w).
    """
    return theta[..., _FULL_FROM_TRIU.to(theta.device)].unflatten(-1, (4, 4))


def vec_from_a(A: Tensor) -> Tensor:
    """Inverse of `a_from_vec`: (..., 4, 4) symmetric -> (..., 10) upper triangle."""
    return A[..., _TRIU_ROWS.to(A.device), _TRIU_COLS.to(A.device)]


def a_from_quat(q: Tensor) -> Tensor:
    """The smooth global section g(q) = I - q q^T (paper eq. 12); g(q) = g(-q).

    Args:
        q: (..., 4) unit quaternions (x, y, z, w).

    Returns:
        (..., 4, 4) symmetric matrices with eigenvalues (0, 1, 1, 1), q spanning the 0-eigenspace.
    """
    eye = torch.eye(4, dtype=q.dtype, device=q.device)
    return eye - q.unsqueeze(-1) * q.unsqueeze(-2)


def a_min_eigvec(A: Tensor, solver: str = "auto") -> tuple[Tensor, Tensor]:
    """Eigenvalues and the minimum eigenvector of symmetric 4x4 matrices (paper eqs. 9, 11).

    Args:
        A: (..., 4, 4) symmetric matrices, float32 or float64.
        solver: the forward of `rotlearn.geometry.sym4_eigh_min` (its `method`): "jacobi" (the
            batched Jacobi solver), "eigh" (torch.linalg.eigh) or "auto" (eigh below
            `rotlearn.geometry.eigen4.EIGH_BELOW` matrices, jacobi from there on). The backward
            is the same for all three: the analytic gradient of eq. 9, finite where eigenvalues
            coincide (torch.linalg.eigh's own backward is NaN there, e.g. for A = cI).

    Returns:
        eigenvalues (..., 4) in ascending order, and q (..., 4), the unit eigenvector of the
        smallest one as a quaternion (x, y, z, w) with canonical sign (w >= 0).
    """
    return sym4_eigh_min(A, check=False, method=solver)


@register_head
class AHead(RotationHead):
    """(..., 10) -> symmetric A (eq. 8) -> q = argmin_{|q|=1} q^T A q (eq. 11) -> R(q)."""

    name = "a"
    out_dim = 10
    defines_belief = True

    def __init__(self, solver: str = "auto") -> None:
        """Args:
        solver: `rep.solver`, one of `SOLVERS` (see `a_min_eigvec`). "fast", the name earlier
            versions saved, is read as "auto" (the same computation) with a DeprecationWarning.
        """
        super().__init__()
        if solver in DEPRECATED_SOLVERS:
            new = DEPRECATED_SOLVERS[solver]
            warnings.warn(
                f"rep.solver={solver} is deprecated: it is read as rep.solver={new} (the same "
                f"solver); write {new}",
                DeprecationWarning,
                stacklevel=2,
            )
            solver = new
        if solver not in SOLVERS:
            raise ConfigError("solver", f"must be one of {', '.join(SOLVERS)}, got {solver!r}")
        self.solver = solver

    def extra_repr(self) -> str:
        return f"out_dim={self.out_dim}, solver={self.solver}"

    def forward(self, raw: Tensor) -> RotationPrediction:
        A = a_from_vec(raw)
        eigenvalues, q = a_min_eigvec(A, self.solver)
        return RotationPrediction(R=quat_to_rotmat(q), raw=raw, q=q, A=A, eigenvalues=eigenvalues)
