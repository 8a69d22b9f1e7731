"""The paper's A representation: a symmetric 4x4 matrix whose minimum eigenvector is the rotation.

Paper section III: A(theta) fills a symmetric matrix from 10 numbers (eq. 8); the rotation is the
unit quaternion minimising q^T A q (eq. 11), i.e. the eigenvector of A's smallest eigenvalue, with
sign fixed so that w >= 0; its derivative is eq. 9. The smooth global section is g(q) = I - q q^T
(eq. 12). Quaternions are scalar last (x, y, z, w); A's rows and columns are in that order.
"""

from __future__ import annotations

import torch
from torch import Tensor

from rotlearn.geometry.eigen4 import METHODS, sym4_eigh_min
from rotlearn.geometry.shapes import require_shape

__all__ = ["a_from_quat", "a_from_vec", "symmatrixvec_to_quat", "vec_from_a"]

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
        (..., 4, 4) symmetric matrices A, rows and columns in quaternion order (x, y, z, w), in
        theta's dtype and on its device.
    """
    require_shape(theta, (10,), "theta")
    return theta.index_select(-1, _full_from_triu(theta.device)).unflatten(-1, (4, 4))


_INDEX_ON: dict[torch.device, Tensor] = {}  # _FULL_FROM_TRIU per device, made once


def _full_from_triu(device: torch.device) -> Tensor:
    """`_FULL_FROM_TRIU` on `device`, without a host-to-device copy per call (a sync on CUDA).

    index_select, not theta[..., index]: its backward (index_add) is ~4x faster on the CPU than
    advanced indexing's (index_put with accumulation), the same numbers (issue 26)."""
    if torch.compiler.is_compiling():  # a constant of the graph
        return _FULL_FROM_TRIU.to(device)
    index = _INDEX_ON.get(device)
    if index is None:
        index = _INDEX_ON[device] = _FULL_FROM_TRIU.to(device)
    return index


def vec_from_a(A: Tensor) -> Tensor:
    """Inverse of `a_from_vec`: (..., 4, 4) symmetric -> (..., 10) upper triangle (eq. 8)."""
    require_shape(A, (4, 4), "A")
    return A[..., _TRIU_ROWS.to(A.device), _TRIU_COLS.to(A.device)]


def a_from_quat(q: Tensor) -> Tensor:
    """The smooth global section g(q) = I - q q^T (paper eq. 12); g(q) = g(-q).

    Args:
        q: (..., 4) unit quaternions (x, y, z, w).

    Returns:
        (..., 4, 4) symmetric matrices with eigenvalues (0, 1, 1, 1), q spanning the 0-eigenspace.
    """
    require_shape(q, (4,), "q")
    eye = torch.eye(4, dtype=q.dtype, device=q.device)
    return eye - q.unsqueeze(-1) * q.unsqueeze(-2)


def symmatrixvec_to_quat(
    theta: Tensor, *, solver: str = "auto", return_eigenvalues: bool = False
) -> Tensor | tuple[Tensor, Tensor]:
    """Unit quaternions from 10-vectors of the A representation: the one-call map of the A layer.

    theta -> A(theta) (paper eq. 8) -> q = argmin_{|q| = 1} q^T A q (eq. 11), the eigenvector of
    A's smallest eigenvalue. Differentiable: the analytic gradient of eq. 9, finite where
    eigenvalues coincide (`rotlearn.geometry.sym4_eigh_min`; torch.linalg.eigh's is NaN there).
    Works under `torch.func.vmap`/`grad` and `torch.compile`. No host synchronisation, no input
    check (NaN in, NaN out with the "jacobi" solver).

    Args:
        theta: (..., 10) [a00, a01, a02, a03, a11, a12, a13, a22, a23, a33], any batch shape,
            float32 or float64 (float16/bfloat16 only under autocast, see below).
        solver: "auto" (the batched Jacobi solver on its fused kernel: C on the CPU, Triton on
            CUDA; where none runs, torch.linalg.eigh's forward below
            `rotlearn.geometry.eigen4.EIGH_BELOW` matrices and Jacobi from there on), "jacobi" or
            "eigh". The backward is the same for all three.
        return_eigenvalues: also return A's eigenvalues (the Bingham belief's dispersion, paper
            III-C, is l1 - l4, l1 - l3, l1 - l2).

    Returns:
        q: (..., 4) unit quaternions (x, y, z, w), sign canonical (w >= 0; ties by the first
            nonzero of w, x, y, z), in theta's dtype; under autocast (CPU or CUDA) float32.
        eigenvalues: (..., 4) ascending, only with `return_eigenvalues=True`; same dtype as q.

    Raises:
        ValueError: theta's last dimension is not 10, an unknown solver, or a dtype other than
            float32/float64 outside autocast.
    """
    if solver not in METHODS:
        raise ValueError(f"solver must be one of {', '.join(METHODS)}, got {solver!r}")
    eigenvalues, q = sym4_eigh_min(a_from_vec(theta), check=False, method=solver)
    return (q, eigenvalues) if return_eigenvalues else q
