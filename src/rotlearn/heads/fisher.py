"""The matrix Fisher head (Mohlin, Sullivan & Bianchi, NeurIPS 2020): 9 numbers -> F -> belief.

The network outputs F (..., 3, 3) read row-major, like SVD-9D; the rotation is F's mode, the same
special orthogonalisation as SVD-9D, and F defines the matrix Fisher belief
p(R) ~ exp(tr(F^T R)), which is the Bingham belief of A = -K(F) (`rotlearn.fisher`). So the
prediction carries both parameterisations, and everything built on A (`loss=bingham`, the DT and
eigen-gap scores, the OOD scores, sampling) works on this head as on the A head, with F's proper
singular values in the eigen-gaps' role: DT = -4 (s1 + s2 + s3), eigen-gap 2 (s2 + s3).
"""

from __future__ import annotations

from torch import Tensor

from rotlearn.fisher import bingham_from_fisher, eigenvalues_from_fisher
from rotlearn.geometry import special_orthogonalize
from rotlearn.geometry.autocast import float32_under_autocast
from rotlearn.heads.base import RotationHead, RotationPrediction, register_head

__all__ = ["FisherHead"]


@register_head
class FisherHead(RotationHead):
    """(..., 9) read row-major as F (..., 3, 3) -> R = `rotlearn.fisher.mode(F)` (SVD-9D), with
    the belief: F, A = `bingham_from_fisher(F)` and A's ascending eigenvalues in closed form
    (`eigenvalues_from_fisher`)."""

    name = "fisher"
    out_dim = 9
    defines_belief = True
    defines_fisher = True

    @float32_under_autocast
    def forward(self, raw: Tensor) -> RotationPrediction:
        F = raw.unflatten(-1, (3, 3))
        return RotationPrediction(  # unchecked: no host synchronisation on the hot path
            R=special_orthogonalize(F),  # = rotlearn.fisher.mode(F)
            raw=raw,
            A=bingham_from_fisher(F, check=False),
            eigenvalues=eigenvalues_from_fisher(F, check=False),
            F=F,
        )
