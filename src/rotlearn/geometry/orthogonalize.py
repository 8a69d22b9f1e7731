"""SVD orthogonalisation with det = +1 (the SVD-9D map of Levinson et al., NeurIPS 2020)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from rotlearn.geometry.autocast import float32_under_autocast
from rotlearn.geometry.shapes import require_shape

__all__ = ["special_orthogonalize"]


class _SpecialOrthogonalize(torch.autograd.Function):
    """R = U diag(1, 1, det(U V^T)) V^T with the polar-factor backward.

    Writing M = U' S' V^T with U' = U D, S' = D S (D = diag(1, 1, d)), R = U' V^T and
        dL/dM = U' K V^T,   K_ij = (G_ij - G_ji) / (s'_i + s'_j),   G = U'^T (dL/dR) V.
    Only sums s'_i + s'_j appear, never differences, so repeated singular values (e.g. M already a
    rotation) are harmless, unlike `torch.linalg.svd`'s backward. The sums vanish only where the
    map itself is discontinuous (s2 == s3 with d = -1); there they are clamped to +-gap_eps.

    New-style Function (forward without ctx, `setup_context`), so torch.func (vmap, grad) and
    torch.compile trace it; the vmap rule is generated. Outputs: R and the factors (U', S', V^T)
    the backward needs (not differentiable).
    """

    generate_vmap_rule = True

    @staticmethod
    def forward(M: Tensor, gap_eps: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        U, S, Vh = torch.linalg.svd(M)
        d = torch.linalg.det(U @ Vh)
        flip = torch.ones_like(S)
        flip[..., 2] = d.sign().where(d != 0, torch.ones_like(d))
        U = U * flip.unsqueeze(-2)
        return U @ Vh, U, S * flip, Vh

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: tuple[Tensor, ...]) -> None:
        _, U, S, Vh = output
        ctx.mark_non_differentiable(U, S, Vh)
        ctx.save_for_backward(U, S, Vh)
        ctx.gap_eps = inputs[1]

    @staticmethod
    def backward(ctx: Any, grad_R: Tensor, *_: Any) -> tuple[Tensor, None]:
        U, S, Vh = ctx.saved_tensors
        with torch.autocast(grad_R.device.type, enabled=False):  # the products in float32
            G = U.transpose(-1, -2) @ grad_R @ Vh.transpose(-1, -2)
            sums = S.unsqueeze(-1) + S.unsqueeze(-2)
            sign = torch.where(sums < 0, -torch.ones_like(sums), torch.ones_like(sums))
            sums = sign * sums.abs().clamp_min(ctx.gap_eps)
            K = (G - G.transpose(-1, -2)) / sums
            return U @ K @ Vh, None


@float32_under_autocast
def special_orthogonalize(M: Tensor, gap_eps: float = 1e-8) -> Tensor:
    """The rotation closest to M in Frobenius norm (SVD orthogonalisation with det fixed to +1).

    Args:
        M: (..., 3, 3) matrices, any batch shape, float32 or float64.
        gap_eps: lower bound on |s_i + s_j| in the backward (see `_SpecialOrthogonalize`), > 0.

    Returns:
        (..., 3, 3) rotation matrices in M's dtype; under autocast (CPU or CUDA) float32 (the
        SVD has no bfloat16 kernel, and a bfloat16 rotation is orthogonal only to ~4e-3). The
        backward is finite for repeated singular values. Works under torch.func.vmap/grad and
        torch.compile.
    """
    require_shape(M, (3, 3), "M")
    if not gap_eps > 0.0:  # 0 or less: the backward divides by zero at repeated singular values
        raise ValueError(f"gap_eps must be > 0, got {gap_eps}")
    return _SpecialOrthogonalize.apply(M, gap_eps)[0]
