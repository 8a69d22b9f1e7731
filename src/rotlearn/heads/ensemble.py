"""The head of an ensemble of belief heads: the product of the members' beliefs (paper V-A).

Not a `rep=` option: an ensemble is assembled from trained runs (`rotlearn.load([run, ...])`,
`rotlearn-eval ckpt=[run, ...]`), each member keeping its own head and its own post-hoc
temperature. See `rotlearn.bingham.product` for the belief (A = sum of the members' A, the
product of their Bingham densities) and its relation to the paper's inertia matrix.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from rotlearn.bingham.product import product_belief
from rotlearn.geometry import quat_to_rotmat, sym4_eigh_min
from rotlearn.geometry.autocast import float32_under_autocast
from rotlearn.heads.base import RotationHead, RotationPrediction

__all__ = ["EnsembleHead"]


class EnsembleHead(RotationHead):
    """K belief heads -> one prediction whose belief is the sum of theirs.

    Input (..., K, d): member k's network output in row k (d = the largest member's out_dim;
    a smaller member reads its first out_dim numbers). Output: A = sum_k A_k / T_k (each
    member's belief tempered by its own temperature), its eigenvalues and minimum eigenvector (q,
    R), the members' quaternions in `members` (K, ..., 4), and raw the (..., K d) input flattened
    (so `raw_norm` is the norm of all the members' outputs).

    Args:
        heads: the members' heads, each defining a belief (`defines_belief`).
        temperatures: each member's post-hoc temperature T_k > 0 (default 1).
    """

    name = "ensemble"
    defines_belief = True
    defines_members = True

    def __init__(self, heads: Sequence[RotationHead], temperatures: Sequence[float] | None = None):
        super().__init__()
        heads = list(heads)
        if not heads:
            raise ValueError("an ensemble needs at least one member")
        lacking = [h.name or type(h).__name__ for h in heads if not h.defines_belief]
        if lacking:
            raise ValueError(
                f"every ensemble member needs a head with a belief (rep=a or fisher); {lacking} "
                "have none"
            )
        temperatures = [1.0] * len(heads) if temperatures is None else list(temperatures)
        if len(temperatures) != len(heads) or not all(t > 0 for t in temperatures):
            raise ValueError(f"need one temperature > 0 per member, got {temperatures}")
        self.heads = nn.ModuleList(heads)
        self.temperatures = [float(t) for t in temperatures]
        self.out_dim = max(h.out_dim for h in heads)

    def extra_repr(self) -> str:
        return f"members={len(self.heads)}, temperatures={self.temperatures}"

    @float32_under_autocast
    def forward(self, raw: Tensor) -> RotationPrediction:
        if raw.shape[-2] != len(self.heads):
            raise ValueError(
                f"expected (..., {len(self.heads)}, d) outputs, got {tuple(raw.shape)}"
            )
        members = [
            head(raw[..., k, : head.out_dim]).with_temperature(t)
            for k, (head, t) in enumerate(zip(self.heads, self.temperatures, strict=True))
        ]
        A = product_belief(torch.stack([m.A for m in members]))
        eigenvalues, q = sym4_eigh_min(A, check=False)
        return RotationPrediction(
            R=quat_to_rotmat(q), raw=raw.flatten(-2), q=q, A=A, eigenvalues=eigenvalues,
            members=torch.stack([m.q for m in members]),
        )  # fmt: skip
