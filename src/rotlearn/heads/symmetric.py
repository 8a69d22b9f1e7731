"""The paper's representation: a symmetric 4x4 matrix A whose minimum eigenvector is the rotation.

Paper section III: A(theta) fills a symmetric matrix from 10 numbers (eq. 8); the rotation is the
unit quaternion minimising q^T A q (eq. 6), i.e. the eigenvector of A's smallest eigenvalue
(eq. 11), with sign fixed so that w >= 0. The maps themselves (eq. 8, eq. 12, the one-call
`symmatrixvec_to_quat`) live in `rotlearn.geometry`; this module is the head around them.
"""

from __future__ import annotations

import warnings

from torch import Tensor

from rotlearn.errors import ConfigError
from rotlearn.geometry import a_from_vec, quat_to_rotmat, sym4_eigh_min
from rotlearn.geometry.autocast import float32_under_autocast
from rotlearn.geometry.eigen4 import METHODS
from rotlearn.heads.base import RotationHead, RotationPrediction, register_head

__all__ = ["SOLVERS", "AHead", "a_min_eigvec"]

SOLVERS = METHODS  # rep.solver: the `method` of rotlearn.geometry.sym4_eigh_min
DEPRECATED_SOLVERS = {"fast": "auto"}  # names that configs saved by earlier versions hold


def a_min_eigvec(A: Tensor, solver: str = "auto") -> tuple[Tensor, Tensor]:
    """Eigenvalues and the minimum eigenvector of symmetric 4x4 matrices (paper eqs. 9, 11).

    Args:
        A: (..., 4, 4) symmetric matrices, float32 or float64.
        solver: the forward of `rotlearn.geometry.sym4_eigh_min` (its `method`): "jacobi" (the
            batched Jacobi solver), "eigh" (torch.linalg.eigh) or "auto" (jacobi on its fused
            kernel, C on the CPU and Triton on CUDA; where none runs, eigh below
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

    @float32_under_autocast
    def forward(self, raw: Tensor) -> RotationPrediction:
        A = a_from_vec(raw)
        eigenvalues, q = a_min_eigvec(A, self.solver)
        return RotationPrediction(R=quat_to_rotmat(q), raw=raw, q=q, A=A, eigenvalues=eigenvalues)
