"""The belief of an ensemble (`rotlearn.bingham.product`): the product of the members' beliefs."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from rotlearn import bingham as bh
from rotlearn.geometry import quat_normalize
from tests.conftest import gen

F64 = torch.float64


def _members(seed: int, k: int, b: int, dtype=F64) -> torch.Tensor:
    g = gen(seed)
    M = torch.randn(k, b, 4, 4, generator=g, dtype=F64)
    return (M @ M.mT).to(dtype)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16), k=st.integers(1, 5))
def test_the_product_density_is_the_bingham_of_the_sum(seed, k):
    """log prod_k p(x; A_k) - log p(x; sum A_k) does not depend on x (the normalisers only)."""
    A = _members(seed, k, 3)
    x = quat_normalize(torch.randn(6, 3, 4, generator=gen(seed + 1), dtype=F64))
    product = bh.product_belief(A)
    torch.testing.assert_close(product, A.sum(0))
    members = sum(bh.log_prob(A[i], x) for i in range(k))
    difference = members - bh.log_prob(product, x)
    torch.testing.assert_close(difference, difference[:1].expand_as(difference))


def test_isotropic_members_give_the_inertia_matrix():
    """A_k = c (I - q_k q_k^T): the sum is c (K I - M), M = sum q_k q_k^T; the ensemble's mode is
    M's largest eigenvector and its DT is -c (4 mu_1 - K)."""
    c, K = 50.0, 4
    q = quat_normalize(torch.tensor([[0.0, 0, 0, 1], [0.1, 0, 0, 1], [0, 0.15, 0, 1],
                                     [0, 0, -0.05, 1]], dtype=F64))  # fmt: skip
    eye = torch.eye(4, dtype=F64)
    A = c * (eye - q[:, :, None] * q[:, None, :])
    total = bh.product_belief(A)
    M = (q[:, :, None] * q[:, None, :]).sum(0)
    torch.testing.assert_close(total, c * (K * eye - M))
    mu, vectors = torch.linalg.eigh(M)
    mode = bh.mode(total)
    assert float((mode * vectors[:, -1]).sum().abs()) == pytest.approx(1.0, abs=1e-12)
    assert float(bh.dt_score(total)) == pytest.approx(-c * (4 * float(mu[-1]) - K), rel=1e-10)
    # members that agree give the sharpest ensemble: DT = -3 c K
    agree = c * (eye - q[:1, :, None] * q[:1, None, :]).expand(K, 4, 4)
    assert float(bh.dt_score(bh.product_belief(agree))) == pytest.approx(-3 * c * K)


def test_disagreement_is_the_largest_angle_to_the_ensemble():
    half = math.radians(10.0) / 2
    q = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64)
    members = torch.stack([q, torch.tensor([math.sin(half), 0, 0, math.cos(half)], dtype=F64),
                           -q])  # fmt: skip
    assert float(bh.disagreement(members, q)) == pytest.approx(10.0, abs=1e-9)
    assert float(bh.disagreement(members[[0, 2]], q)) == pytest.approx(0.0, abs=1e-5)  # -q = q
    with pytest.raises(ValueError, match="members"):
        bh.disagreement(members[:, :3], q)


def test_the_product_is_differentiable():
    A = _members(3, 2, 2).requires_grad_()
    assert torch.autograd.gradcheck(lambda a: bh.dt_score(bh.product_belief(a)), (A,))
