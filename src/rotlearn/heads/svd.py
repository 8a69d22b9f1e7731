"""SVD-9D: special orthogonalisation of a 3x3 matrix (Levinson et al., NeurIPS 2020)."""

from __future__ import annotations

import torch
from torch import Tensor

from rotlearn.heads.base import RotationHead, RotationPrediction, register_head

__all__ = ["SVD9DHead", "special_orthogonalize"]


class _SpecialOrthogonalize(torch.autograd.Function):
    """R = U diag(1, 1, det(U V^T)) V^T with the polar-factor backward.

    Writing M = U' S' V^T with U' = U D, S' = D S (D = diag(1, 1, d)), R = U' V^T and
        dL/dM = U' K V^T,   K_ij = (G_ij - G_ji) / (s'_i + s'_j),   G = U'^T (dL/dR) V.
    Only sums s'_i + s'_j appear, never differences, so repeated singular values (e.g. M already a
    rotation) are harmless, unlike `torch.linalg.svd`'s backward. The sums vanish only where the
    map itself is discontinuous (s2 == s3 with d = -1); there they are clamped to +-gap_eps.
    """

    @staticmethod
    def forward(ctx, M: Tensor, gap_eps: float) -> Tensor:
        U, S, Vh = torch.linalg.svd(M)
        d = torch.linalg.det(U @ Vh)
        flip = torch.ones_like(S)
        flip[..., 2] = d.sign().where(d != 0, torch.ones_like(d))
        U = U * flip.unsqueeze(-2)
        ctx.save_for_backward(U, S * flip, Vh)
        ctx.gap_eps = gap_eps
        return U @ Vh

    @staticmethod
    def backward(ctx, grad_R: Tensor) -> tuple[Tensor, None]:
        U, S, Vh = ctx.saved_tensors
        G = U.transpose(-1, -2) @ grad_R @ Vh.transpose(-1, -2)
        sums = S.unsqueeze(-1) + S.unsqueeze(-2)
        sign = torch.where(sums < 0, -torch.ones_like(sums), torch.ones_like(sums))
        sums = sign * sums.abs().clamp_min(ctx.gap_eps)
        K = (G - G.transpose(-1, -2)) / sums
        return U @ K @ Vh, None


def special_orthogonalize(M: Tensor, gap_eps: float = 1e-8) -> Tensor:
    """The rotation closest to M in Frobenius norm (SVD orthogonalisation with det fixed to +1).

    Args:
        M: (..., 3, 3) matrices.
        gap_eps: lower bound on |s_i + s_j| in the backward (see `_SpecialOrthogonalize`).

    Returns:
        (..., 3, 3) rotation matrices. The backward is finite for repeated singular values.
    """
    return _SpecialOrthogonalize.apply(M, gap_eps)


@register_head
class SVD9DHead(RotationHead):
    """(..., 9) read row-major as a 3x3 matrix -> `special_orthogonalize`."""

    name = "svd9d"
    out_dim = 9

    def forward(self, raw: Tensor) -> RotationPrediction:
        return RotationPrediction(R=special_orthogonalize(raw.unflatten(-1, (3, 3))), raw=raw)
