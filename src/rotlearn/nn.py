"""Drop-in rotation layers for any PyTorch model: tensor in, tensor out (usable in nn.Sequential).

Each layer is stateless (no parameters) and wraps one map of `rotlearn.geometry`, so a layer and
its functional form always agree. Quaternions are scalar last (x, y, z, w). Every layer takes any
batch shape, float32 or float64, and works under autocast (it computes and returns float32 there:
a rotation in bfloat16 is orthogonal only to ~4e-3), torch.func (vmap, grad) and torch.compile.

Example::

    model = nn.Sequential(nn.Linear(32, 64), nn.ReLU(), nn.Linear(64, 10), ALayer())
    q = model(x)  # (B, 4) unit quaternions
"""

from __future__ import annotations

from torch import Tensor, nn

from rotlearn.geometry import sixd_to_rotmat, special_orthogonalize, symmatrixvec_to_quat
from rotlearn.geometry.eigen4 import METHODS
from rotlearn.geometry.shapes import require_shape

__all__ = ["ALayer", "SVDToRotmat", "SixDToRotmat", "SymmetricMatrixToQuat"]


class ALayer(nn.Module):
    """The paper's A representation as a layer: (..., 10) -> (..., 4) unit quaternions.

    theta fills a symmetric 4x4 matrix A (paper eq. 8; order a00 a01 a02 a03 a11 a12 a13 a22 a23
    a33, rows and columns in (x, y, z, w) order); the output is the unit eigenvector of A's
    smallest eigenvalue (eq. 11), sign canonical (w >= 0). Its gradient is eq. 9, finite where
    eigenvalues coincide. The eigenvalues (ascending) describe the Bingham belief A encodes
    (dispersion l1 - l4, l1 - l3, l1 - l2; paper III-C).

    Args:
        return_eigenvalues: also return the eigenvalues: forward gives (q, eigenvalues).
        solver: "auto", "jacobi" or "eigh" (see `rotlearn.geometry.symmatrixvec_to_quat`).

    Shapes: input (..., 10); output q (..., 4) [and eigenvalues (..., 4)], in the input's dtype
    (float32 under autocast).
    """

    def __init__(self, return_eigenvalues: bool = False, solver: str = "auto") -> None:
        super().__init__()
        if solver not in METHODS:
            raise ValueError(f"solver must be one of {', '.join(METHODS)}, got {solver!r}")
        self.return_eigenvalues = return_eigenvalues
        self.solver = solver

    def forward(self, theta: Tensor) -> Tensor | tuple[Tensor, Tensor]:
        return symmatrixvec_to_quat(
            theta, solver=self.solver, return_eigenvalues=self.return_eigenvalues
        )

    def extra_repr(self) -> str:
        return f"return_eigenvalues={self.return_eigenvalues}, solver={self.solver!r}"


SymmetricMatrixToQuat = ALayer  # the descriptive name of the same layer


class SixDToRotmat(nn.Module):
    """The 6D representation (Zhou et al., CVPR 2019) as a layer: (..., 6) -> (..., 3, 3).

    Gram-Schmidt on the two 3-vectors, which become the first two COLUMNS of the rotation
    (`rotlearn.geometry.sixd_to_rotmat`). Output in the input's dtype (float32 under autocast).
    """

    def forward(self, v: Tensor) -> Tensor:
        return sixd_to_rotmat(v)


class SVDToRotmat(nn.Module):
    """The SVD-9D representation (Levinson et al., NeurIPS 2020) as a layer: (..., 9) -> 3x3.

    The 9 numbers, read row-major as a 3x3 matrix M, map to the rotation closest to M in Frobenius
    norm (`rotlearn.geometry.special_orthogonalize`; the backward is finite for repeated
    singular values). Output (..., 3, 3) in the input's dtype (float32 under autocast).
    """

    def forward(self, m: Tensor) -> Tensor:
        require_shape(m, (9,), "m")
        return special_orthogonalize(m.unflatten(-1, (3, 3)))
