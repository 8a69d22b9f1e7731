"""Representation heads: every head gives rotations; the A head's section; 6D; SVD-9D backward."""

from __future__ import annotations

import math
import re

import pytest
import torch

from rotlearn import bingham, fisher
from rotlearn.geometry import (
    a_from_quat,
    a_from_vec,
    quat_to_rotmat,
    rotmat_to_quat,
    sixd_to_rotmat,
    special_orthogonalize,
    symmatrixvec_to_quat,
    vec_from_a,
)
from rotlearn.heads import (
    HEADS,
    AHead,
    FisherHead,
    QuatHead,
    RotationHead,
    SixDHead,
    SVD9DHead,
    a_min_eigvec,
    make_head,
)
from tests.conftest import ATOL, DTYPES, assert_rotation, randn, scipy_rotmats

F64 = torch.float64
HEAD_NAMES = sorted(HEADS)


def test_registry_holds_the_five_heads():
    assert set(HEADS) == {"quat", "sixd", "a", "svd9d", "fisher"}
    dims = {"quat": 4, "sixd": 6, "a": 10, "svd9d": 9, "fisher": 9}
    for name, cls in HEADS.items():
        assert issubclass(cls, RotationHead)
        assert cls.name == name and cls.out_dim == dims[name]
    assert {name for name, cls in HEADS.items() if cls.defines_belief} == {"a", "fisher"}
    assert {name for name, cls in HEADS.items() if cls.defines_fisher} == {"fisher"}


# ---------------------------------------------------------------------------------------------
# every head
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("lead", [(7,), (2, 3)])
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("name", HEAD_NAMES)
def test_head_outputs_rotations(name, dtype, lead):
    head = make_head(name)
    raw = randn(sum(map(ord, name)), (*lead, head.out_dim), dtype)
    pred = head(raw)
    assert pred.R.shape == (*lead, 3, 3) and pred.R.dtype == dtype
    assert pred.raw is raw
    assert_rotation(pred.R, ATOL[dtype])
    q = pred.q
    assert q.shape == (*lead, 4) and q.dtype == dtype
    torch.testing.assert_close(
        q.norm(dim=-1), torch.ones(lead, dtype=dtype), atol=ATOL[dtype], rtol=0
    )
    assert (q[..., 3] >= 0).all()
    torch.testing.assert_close(quat_to_rotmat(q), pred.R, atol=ATOL[dtype], rtol=0)
    # detach keeps the values and cuts the graph
    cut = head(raw.clone().requires_grad_()).detach()
    assert not cut.R.requires_grad and torch.equal(cut.R, pred.R)


@pytest.mark.parametrize("name", HEAD_NAMES)
def test_head_gradcheck(name):
    head = make_head(name)
    raw = randn(100 + len(name), (3, head.out_dim)).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: head(x).R, (raw,))


def test_make_head_unknown_name_lists_allowed():
    with pytest.raises((KeyError, ValueError)) as info:
        make_head("euler")
    message = str(info.value)
    assert "euler" in message
    words = set(re.findall(r"[A-Za-z0-9_]+", message.split("allowed")[-1]))
    assert set(HEAD_NAMES) <= words


@pytest.mark.parametrize("name", HEAD_NAMES)
def test_make_head_out_dim(name):
    head = make_head(name, out_dim=HEADS[name].out_dim)
    assert isinstance(head, HEADS[name])
    with pytest.raises(ValueError):
        make_head(name, out_dim=HEADS[name].out_dim + 1)


# ---------------------------------------------------------------------------------------------
# the A head (symmetric matrix, paper eqs. 8-13)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
def test_a_head_min_eigenvector(dtype):
    raw = randn(3, (64, 10), dtype)
    pred = AHead()(raw)
    A, lam, q = pred.A, pred.eigenvalues, pred.q
    assert torch.equal(A, a_from_vec(raw))
    assert (lam[..., 1:] >= lam[..., :-1]).all()  # ascending
    tol = 1e-4 if dtype == torch.float32 else 1e-10  # |A| ~ 3: eigen-solver rounding
    torch.testing.assert_close(lam, torch.linalg.eigvalsh(A), atol=tol, rtol=0)
    # A q = l1 q (the smallest eigenvalue), and q^T A q is the minimum over unit vectors
    Aq = (A @ q.unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(Aq, lam[..., :1] * q, atol=tol, rtol=0)
    v = randn(4, (1000, 64, 4), dtype)
    v = v / v.norm(dim=-1, keepdim=True)
    rayleigh = torch.einsum("kbi,bij,kbj->kb", v, A, v)
    assert (rayleigh >= lam[..., 0] - tol).all()
    lam2, q2 = a_min_eigvec(A)
    torch.testing.assert_close(q2, q, atol=0, rtol=0)
    torch.testing.assert_close(lam2, lam, atol=0, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_a_head_smooth_global_section(dtype):
    # f(g(R)) = R with g(q) = I - q q^T (paper eqs. 12-13), including 0 and 180 degrees
    special = torch.stack(
        [
            torch.eye(3, dtype=F64),
            torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=F64)),
            torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=F64)),
        ]
    )
    R = torch.cat([scipy_rotmats(5, 64), special]).to(dtype)
    q = rotmat_to_quat(R)
    A = a_from_quat(q)
    torch.testing.assert_close(A, a_from_quat(-q), atol=0, rtol=0)  # g(q) = g(-q)
    pred = AHead()(vec_from_a(A))
    torch.testing.assert_close(pred.R, R, atol=10 * ATOL[dtype], rtol=0)
    expected_lam = torch.tensor([0.0, 1.0, 1.0, 1.0], dtype=dtype).expand(R.shape[0], 4)
    torch.testing.assert_close(pred.eigenvalues, expected_lam, atol=10 * ATOL[dtype], rtol=0)


# ---------------------------------------------------------------------------------------------
# the 6D head
# ---------------------------------------------------------------------------------------------


def normalize(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("dtype", DTYPES)
def test_sixd_columns_as_documented(dtype):
    v = randn(6, (2, 5, 6), dtype)
    R = SixDHead()(v).R
    torch.testing.assert_close(R, sixd_to_rotmat(v), atol=0, rtol=0)
    x = normalize(v[..., 0:3])
    z = normalize(torch.linalg.cross(x, v[..., 3:6]))
    y = torch.linalg.cross(z, x)
    torch.testing.assert_close(R[..., :, 0], x, atol=ATOL[dtype], rtol=0)
    torch.testing.assert_close(R[..., :, 1], y, atol=ATOL[dtype], rtol=0)
    torch.testing.assert_close(R[..., :, 2], z, atol=ATOL[dtype], rtol=0)
    # Gram-Schmidt: y lies in span(v1, v2) on v2's side
    assert ((R[..., :, 1] * v[..., 3:6]).sum(-1) > 0).all()
    # positive scaling of either half does not matter
    scaled = torch.cat((3.0 * v[..., 0:3], 0.5 * v[..., 3:6]), dim=-1)
    torch.testing.assert_close(sixd_to_rotmat(scaled), R, atol=10 * ATOL[dtype], rtol=0)


# ---------------------------------------------------------------------------------------------
# SVD-9D
# ---------------------------------------------------------------------------------------------


def test_gradcheck_special_orthogonalize():
    R = scipy_rotmats(18, 4)
    M_near = (R + 1e-3 * randn(19, (4, 3, 3))).requires_grad_()
    assert torch.autograd.gradcheck(special_orthogonalize, (M_near,))
    M = randn(20, (6, 3, 3))
    assert (torch.linalg.det(M) < 0).any() and (torch.linalg.det(M) > 0).any()  # both branches
    assert torch.autograd.gradcheck(special_orthogonalize, (M.requires_grad_(),))
    head = SVD9DHead()
    raw = randn(21, (4, 9)).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: head(x).R, (raw,))


# ---------------------------------------------------------------------------------------------
# the matrix Fisher head
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
def test_fisher_head_is_svd9d_with_its_belief(dtype):
    """R is the SVD-9D rotation of the same 9 numbers; the belief is F itself, A = -K(F) and A's
    eigenvalues, so the Bingham descriptors read F's proper singular values."""
    raw = randn(25, (2, 6, 9), dtype)
    pred = FisherHead()(raw)
    F = raw.unflatten(-1, (3, 3))
    assert torch.equal(pred.F, F) and torch.equal(pred.R, SVD9DHead()(raw).R)
    torch.testing.assert_close(pred.A, fisher.bingham_from_fisher(F), atol=0, rtol=0)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(pred.eigenvalues, torch.linalg.eigvalsh(pred.A), atol=tol, rtol=0)
    s = fisher.proper_svd(F)[1]
    torch.testing.assert_close(pred.dt, -4 * s.sum(-1), atol=tol, rtol=0)
    torch.testing.assert_close(pred.eigengap, 2 * (s[..., 1] + s[..., 2]), atol=tol, rtol=0)
    torch.testing.assert_close(pred.dt, bingham.dt_score(pred.A), atol=10 * tol, rtol=0)
    # tempering divides F, A and the eigenvalues alike: still one belief
    tempered = pred.with_temperature(4.0)
    torch.testing.assert_close(tempered.A, fisher.bingham_from_fisher(tempered.F))
    assert tempered.R is pred.R


def test_fisher_head_gradcheck_through_its_belief():
    head = FisherHead()
    raw = randn(26, (3, 9)).requires_grad_()
    assert torch.autograd.gradcheck(lambda x: head(x).eigenvalues, (raw,))
    assert torch.autograd.gradcheck(lambda x: head(x).A, (raw,))


# ---------------------------------------------------------------------------------------------
# the quaternion head
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES)
def test_quat_head_sign_invariant(dtype):
    raw = randn(22, (16, 4), dtype)
    head = QuatHead()
    a, b = head(raw), head(-raw)
    torch.testing.assert_close(a.R, b.R, atol=ATOL[dtype], rtol=0)
    torch.testing.assert_close(a.q, b.q, atol=ATOL[dtype], rtol=0)
    torch.testing.assert_close(
        a.q, raw / raw.norm(dim=-1, keepdim=True) * raw[..., 3:].sign(), atol=ATOL[dtype], rtol=0
    )
    # the scale of the raw output does not matter either
    torch.testing.assert_close(head(5.0 * raw).R, a.R, atol=ATOL[dtype], rtol=0)
    assert math.isfinite(a.R.sum().item())


# ---------------------------------------------------------------------------------------------
# every head under mixed precision
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", HEAD_NAMES)
def test_heads_give_float32_rotations_under_autocast(name):
    # a bf16-mixed network hands the head bfloat16 numbers; the head computes in float32
    head = make_head(name)
    raw = randn(22, (16, head.out_dim), torch.float32).to(torch.bfloat16).requires_grad_()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        pred = head(raw)
    for value in (pred.R, pred.q, pred.A, pred.eigenvalues, pred.F):
        assert value is None or value.dtype == torch.float32
    assert_rotation(pred.R.detach(), ATOL[torch.float32])
    reference = head(raw.detach().float())
    torch.testing.assert_close(pred.R, reference.R, atol=1e-6, rtol=0)
    (pred.R * randn(23, (16, 3, 3), torch.float32)).sum().backward()
    assert raw.grad.dtype == torch.bfloat16 and torch.isfinite(raw.grad.float()).all()


def test_a_head_is_the_one_call_map():
    raw = randn(24, (8, 10))
    pred = AHead(solver="jacobi")(raw)
    q, eigenvalues = symmatrixvec_to_quat(raw, solver="jacobi", return_eigenvalues=True)
    assert torch.equal(pred.q, q) and torch.equal(pred.eigenvalues, eigenvalues)


def test_with_temperature_scales_the_belief_and_keeps_the_mode():
    """A / T tempers the Bingham belief: every eigenvalue (so DT, the eigen-gap) scales by 1 / T,
    the rotation does not move; T = 1 and heads without a belief are returned unchanged."""
    raw = torch.randn(7, 10, dtype=torch.float64)
    prediction = make_head("a")(raw)
    tempered = prediction.with_temperature(2.5)
    torch.testing.assert_close(tempered.A * 2.5, prediction.A)
    torch.testing.assert_close(tempered.dt * 2.5, prediction.dt)
    torch.testing.assert_close(tempered.eigengap * 2.5, prediction.eigengap)
    assert tempered.R is prediction.R and tempered.raw is prediction.raw
    assert prediction.with_temperature(1) is prediction
    sixd = make_head("sixd")(torch.randn(3, 6))
    assert sixd.with_temperature(2.0) is sixd
