"""The belief of an ensemble: the product of its members' Bingham beliefs (paper section V-A).

Quaternions are scalar LAST (x, y, z, w); a belief is p(x; A) ~ exp(-x^T A x) (`rotlearn.bingham`).

The product of K Bingham densities is a Bingham density,

    prod_k exp(-x^T A_k x) = exp(-x^T (sum_k A_k) x),

so an ensemble of A heads (or any heads with a Bingham belief) has the belief A = sum_k A_k
(`product_belief`): its mode is the minimum eigenvector of the sum, and its dispersion, DT and
eigen-gaps are those of the sum (`rotlearn.bingham.descriptors`).

Relation to rotation averaging (the paper's reading of DT). Where every member is isotropic
around its own mode q_k with the same concentration c, A_k = c (I - q_k q_k^T) (eigenvalues 0, c,
c, c: dispersion (-c, -c, -c)), the sum is

    A = c (K I - M),     M = sum_k q_k q_k^T,

M the inertia (scatter) matrix of the members' quaternions, whose largest eigenvector is the
chordal L2 mean of the rotations (Markley et al. 2007). A's eigenvalues are c (K - mu_j) for M's
eigenvalues mu_1 >= ... >= mu_4 (sum_j mu_j = K): the ensemble's mode is that mean, its eigen-gaps
c (mu_1 - mu_j) shrink as the members disagree, and DT = tr(Lambda) = -c (4 mu_1 - K) rises from
-3 c K (all agree: mu_1 = K) to 0 (M isotropic). So the ensemble's DT is dispersion thresholding
on the inertia matrix of its members, weighted by each member's own belief where the members are
not isotropic. The members' spread is also read directly: `disagreement`, the largest angle
between a member's mode and the ensemble's.

The members of an ensemble share their training data, so their errors are correlated and the
product is over-confident (about K times too concentrated where they agree); fit its temperature
on held-out data (`rotlearn.bingham.fit_temperature`; `calibrate` does for `rotlearn-eval` of an
ensemble, `rotlearn.inference.Predictor.calibrate` for `rotlearn.load([run, ...])`).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["disagreement", "product_belief"]


def product_belief(A: Tensor) -> Tensor:
    """The Bingham matrix of the product of K beliefs: the sum of their A (module docstring).

    Args:
        A: (K, ..., 4, 4) the members' symmetric matrices, float32 or float64.

    Returns:
        (..., 4, 4) in A's dtype and on its device; differentiable.
    """
    if A.dim() < 3 or A.shape[-2:] != (4, 4):
        raise ValueError(f"A must have shape (K, ..., 4, 4), got {tuple(A.shape)}")
    return A.sum(0)


def disagreement(members: Tensor, q: Tensor) -> Tensor:
    """The largest angle, in degrees, between a member's rotation and the ensemble's.

    Args:
        members: (K, ..., 4) the members' unit quaternions (x, y, z, w; either sign).
        q: (..., 4) the ensemble's unit quaternion.

    Returns:
        (...,) degrees in [0, 180], in the promoted dtype: the rotation angle 2 acos(|<q_k, q>|)
        (computed as 4 atan2(|q_k - s q|, |q_k + s q|), s the sign of <q_k, q>), maxed over k.
    """
    if members.dim() < 2 or len(members) < 1 or members.shape[1:] != q.shape or q.shape[-1] != 4:
        raise ValueError(
            f"members must have shape (K >= 1, *q.shape) with q (..., 4), got "
            f"{tuple(members.shape)} and {tuple(q.shape)}"
        )
    q = q.unsqueeze(0)
    sign = torch.where((members * q).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(q.dtype)
    near, far = (members - sign * q).norm(dim=-1), (members + sign * q).norm(dim=-1)
    return torch.rad2deg(4.0 * torch.atan2(near, far)).amax(0)  # accurate near 0, unlike acos
