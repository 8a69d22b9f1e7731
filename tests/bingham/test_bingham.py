"""Bingham belief from A (paper III-C, eqs. 14-15, 19, 26): normaliser, likelihood, sampling.

References are computed here, independently of the module's Talbot inversion: adaptive scipy
quadrature of the Hopf-coordinate (Bessel) form of N, itself checked against closed forms from
mpmath; quadrature of the density over S^3 in Hopf coordinates; Monte Carlo.
"""

from __future__ import annotations

import itertools
import math
import warnings

import mpmath
import numpy as np
import pytest
import torch
from scipy import integrate, special

from rotlearn import bingham as bh
from rotlearn.errors import ConfigError
from rotlearn.geometry import a_from_quat, quat_to_rotmat
from rotlearn.heads import a_min_eigvec, make_head
from rotlearn.losses import BinghamNLLLoss
from tests.conftest import gen

F32, F64 = torch.float32, torch.float64


# ------------------------------------------------------------------------------ the reference

# Split points for the adaptive quadrature: boundary layers of width ~1/|lam| at both ends.
_SPLITS = sorted({0.0, 0.5, 1.0} | {x for k in range(1, 12) for x in (10.0**-k, 1 - 10.0**-k)})


def _quad(f) -> float:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", integrate.IntegrationWarning)
        return sum(
            integrate.quad(f, lo, hi, epsabs=0.0, epsrel=1e-12, limit=200)[0]
            for lo, hi in itertools.pairwise(_SPLITS)
        )


def ref_log_n_moments(lam3) -> tuple[float, np.ndarray]:
    """log N and E[x_i^2] (input order) for three coefficients <= 0 (fourth 0), probability measure.

    For x uniform on S^3, s = x1^2 + x2^2 ~ U(0, 1) and each pair's angle is uniform, so with the
    coefficients sorted l1 <= l2 <= l3 <= 0 and paired (l1, l2), (l3, 0):
    N = int_0^1 e^{s (l1 + l2)/2} I0(s (l1 - l2)/2) e^{(1-s) l3/2} I0((1-s) l3/2) ds.
    Moments: d/dl of the log integrand; g(z) = 1 - I1(z)/I0(z) avoids the cancellation.
    """
    lam3 = np.asarray(lam3, dtype=float)
    order = np.argsort(lam3)
    l1, l2, l3 = lam3[order]
    b, d = (l2 - l1) / 2, -l3 / 2  # >= 0

    def f(s):
        return special.i0e(s * b) * special.i0e((1 - s) * d) * np.exp(s * l2)

    def g(z):
        return 1.0 - special.i1e(z) / special.i0e(z)

    n = _quad(f)
    m = np.array(
        [
            _quad(lambda s: f(s) * s * g(s * b) / 2),
            _quad(lambda s: f(s) * s * (2 - g(s * b)) / 2),
            _quad(lambda s: f(s) * (1 - s) * g((1 - s) * d) / 2),
        ]
    )
    out = np.empty(3)
    out[order] = m / n
    return math.log(n), out


def _grid() -> np.ndarray:
    mags = [0.0, 1e-3, 0.5, 1.0, 10.0, 100.0, 1e3, 1e4, 1e5, 1e6]
    cases = [list(c) for c in itertools.combinations_with_replacement(mags, 3)]
    cases += [
        [1e4, 1.0, 0.0],
        [1e4, 1e4, 0.0],
        [1e6, 1.0, 0.0],
        [1e-8, 1e-8, 1e6],
        [1e8, 1.0, 0.0],
        [1e8, 1e8, 1e8],
        [1e8, 1e6, 1e3],
        [1e7, 1e7, 0.0],
        [1e-8, 1e8, 1e8],
        [37.0, 37.0 * (1 + 1e-7), 37.0 * (1 - 1e-7)],
        [2500.0, 2500.0 + 1e-3, 0.25],
        [3.0, 1e4, 3.0],
    ]
    rng = np.random.default_rng(1)
    rand = 10.0 ** rng.uniform(-4, 8, (30, 3))
    rand[rng.random((30, 3)) < 0.2] = 0.0
    return -np.concatenate([np.array(cases), rand])


@pytest.fixture(scope="module")
def reference():
    grid = _grid()
    refs = [ref_log_n_moments(lam) for lam in grid]
    return grid, np.array([r[0] for r in refs]), np.array([r[1] for r in refs])


@pytest.mark.parametrize("a", [-0.5, -30.0, -1e4])
def test_reference_matches_closed_forms(a):
    """N(a,0,0) = 1F1(1/2; 2; a), N(a,a,0) = (e^a - 1)/a, N(a,a,a) = e^a 1F1(1/2; 2; -a)."""
    mpmath.mp.dps = 30
    expected = [
        mpmath.log(mpmath.hyp1f1(0.5, 2, a)),
        mpmath.log(mpmath.expm1(a) / a),
        a + mpmath.log(mpmath.hyp1f1(0.5, 2, -a)),
    ]
    for lam, want in zip(([a, 0, 0], [a, a, 0], [a, a, a]), expected, strict=True):
        assert abs(ref_log_n_moments(lam)[0] - float(want)) < 1e-11


# ------------------------------------------------------------------------- normaliser accuracy

TOL_N = {F64: 1e-10, F32: 1e-5}  # relative error of N (specification: 1e-6 and 1e-4)
TOL_MOMENTS = {F64: 1e-8, F32: 2e-5}


@pytest.mark.parametrize("dtype", [F64, F32], ids=str)
def test_log_normalizer_and_gradient_match_reference(reference, dtype):
    grid, log_n_ref, mom_ref = reference
    lam = torch.tensor(grid, dtype=dtype, requires_grad=True)
    log_n = bh.log_normalizer(lam)
    log_n.sum().backward()
    assert log_n.dtype == dtype and lam.grad.dtype == dtype
    rel_n = np.abs(np.expm1(log_n.detach().double().numpy() - log_n_ref))
    rel_m = np.abs(lam.grad.double().numpy() / mom_ref - 1)
    assert rel_n.max() <= TOL_N[dtype], (rel_n.max(), grid[rel_n.argmax()])
    assert rel_m.max() <= TOL_MOMENTS[dtype], (rel_m.max(), grid[rel_m.argmax() // 3])
    n = bh.normalizer(lam.detach()).double().numpy()
    ok = log_n_ref > -80  # where N itself is representable
    np.testing.assert_allclose(n[ok], np.exp(log_n_ref[ok]), rtol=2 * TOL_N[dtype], atol=0)
    torch.testing.assert_close(bh.moments(lam.detach()), lam.grad, rtol=0, atol=0)


@pytest.mark.parametrize("dtype", [F64, F32], ids=str)
def test_zero_coefficients_give_one(dtype):
    assert abs(bh.normalizer(torch.zeros(3, dtype=dtype)).item() - 1) < TOL_N[dtype]
    assert abs(bh.normalizer(torch.zeros(2, 4, dtype=dtype)) - 1).max() < TOL_N[dtype]
    m = bh.moments(torch.zeros(4, dtype=dtype))
    torch.testing.assert_close(m, torch.full((4,), 0.25, dtype=dtype), rtol=0, atol=TOL_N[dtype])
    assert bh.log_normalizer(torch.zeros(0, 5, 3, dtype=dtype)).shape == (0, 5)


def test_gradcheck_float64():
    lam = torch.tensor(
        [[-1.0, -2.0, -3.0], [-1e4, -1.0, -1e-3], [-50.0, -50.0, -0.1], [-1e-3, -7.0, -700.0]],
        dtype=F64,
        requires_grad=True,
    )
    assert torch.autograd.gradcheck(bh.log_normalizer, (lam,), eps=1e-6, atol=1e-8, rtol=1e-6)
    lam4 = torch.tensor([[0.3, -2.0, 1.5, -40.0], [5.0, 5.5, 4.0, 3.0]], dtype=F64)
    assert torch.autograd.gradcheck(bh.log_normalizer, (lam4.requires_grad_(),), atol=1e-8)


@pytest.mark.parametrize("dtype", [F64, F32], ids=str)
def test_four_coefficients_shift_and_permutation(dtype):
    lam3 = torch.tensor([[-3.0, -0.5, -120.0], [-1e4, -1.0, 0.0]], dtype=dtype)
    lam4 = torch.cat((lam3, torch.zeros(2, 1, dtype=dtype)), -1)
    tol = 10 * TOL_N[dtype]
    torch.testing.assert_close(bh.log_normalizer(lam4), bh.log_normalizer(lam3), rtol=0, atol=tol)
    for c in (-7.25, 0.0, 3.5, 1e3):  # N(lam + c) = e^c N(lam)
        shifted = bh.log_normalizer(lam4 + c) - c
        torch.testing.assert_close(shifted, bh.log_normalizer(lam4), rtol=0, atol=tol * (1 + c**2))
    perm = lam4[:, [2, 0, 3, 1]]
    torch.testing.assert_close(bh.log_normalizer(perm), bh.log_normalizer(lam4), rtol=0, atol=tol)
    m4 = bh.moments(perm)
    torch.testing.assert_close(m4.sum(-1), torch.ones(2, dtype=dtype), rtol=0, atol=tol)
    torch.testing.assert_close(m4[:, [1, 3, 0]], bh.moments(lam3), rtol=10 * tol, atol=0)


def test_gradient_at_tied_top_coefficients_is_symmetric():
    lam = torch.tensor([0.0, 0.0, -1.0, -2.0], dtype=F64, requires_grad=True)
    bh.log_normalizer(lam).backward()
    assert lam.grad[0].item() == pytest.approx(lam.grad[1].item(), rel=1e-10)
    assert lam.grad.sum().item() == pytest.approx(1.0, abs=1e-12)
    torch.testing.assert_close(lam.grad, bh.moments(lam.detach()), rtol=0, atol=0)


@pytest.mark.parametrize("dtype", [F64, F32], ids=str)
def test_extreme_coefficients_are_finite(dtype):
    values = [-bh.MAX_DISPERSION, -1e4, -1.0, -1e-12, 0.0]
    lam = torch.tensor(list(itertools.product(values, repeat=3)), dtype=dtype)
    lam.requires_grad_(True)
    log_n = bh.log_normalizer(lam)
    log_n.sum().backward()
    assert torch.isfinite(log_n).all() and torch.isfinite(lam.grad).all()
    assert (log_n <= 1e-6).all() and (lam.grad >= 0).all() and (lam.grad.sum(-1) <= 1 + 1e-5).all()
    # more concentrated -> smaller N
    base = torch.tensor([-1.0, -1.0, -1.0], dtype=dtype)
    assert bh.log_normalizer(base * 10) < bh.log_normalizer(base) < 0


def test_half_precision_is_computed_in_float32():
    lam = torch.tensor([-2.0, -30.0, 0.0])
    out = bh.log_normalizer(lam.half())
    assert out.dtype == torch.float16
    assert abs(out.float() - bh.log_normalizer(lam)) < 1e-2


@pytest.mark.parametrize(
    ("lam", "message"),
    [
        ([[-1.0, -2.0, -3.0], [-1.0, 0.5, -3.0]], r"<= 0.*batch index \(1,\)"),
        (
            [[-1.0, -2.0, -3.0], [-1.0, -2.0, -3 * bh.MAX_DISPERSION]],
            r"below -MAX_DISPERSION.*batch index \(1,\)",
        ),
        ([[-1.0, float("nan"), -3.0], [-1.0, -2.0, -3.0]], r"NaN or Inf at batch index \(0,\)"),
        ([[-1.0, -2.0, -3.0], [-1.0, float("-inf"), -3.0]], r"NaN or Inf at batch index \(1,\)"),
        (
            [[0.0, 1.0, 2.0, 3.0], [2 * bh.MAX_DISPERSION, 0.0, 0.0, 0.0]],
            r"spread.*batch index \(1,\)",
        ),
        ([1.0, 2.0], r"shape"),
    ],
)
def test_bad_coefficients_raise(lam, message):
    with pytest.raises(ValueError, match=message):
        bh.log_normalizer(torch.tensor(lam, dtype=F64))


def test_integer_coefficients_raise():
    with pytest.raises(TypeError, match="floating"):
        bh.log_normalizer(torch.zeros(3, dtype=torch.long))


# ---------------------------------------------------------------------------- A and descriptors


def rotations(n: int, seed: int, dtype=F64) -> torch.Tensor:
    return torch.linalg.qr(torch.randn(n, 4, 4, generator=gen(seed), dtype=dtype))[0]


def a_from_dispersion(lam: torch.Tensor, V: torch.Tensor, l1: float = 0.7) -> torch.Tensor:
    """A with eigenvalues (l1, l1 - lam3, l1 - lam2, l1 - lam1) on the columns of V."""
    ev = torch.cat((torch.full_like(lam[..., :1], l1), l1 - lam.flip(-1)), -1)
    return V @ torch.diag_embed(ev) @ V.mT


def test_descriptors_of_constructed_matrices():
    lam = torch.tensor([[-20.0, -5.0, -1.0], [-1e4, -100.0, -0.5], [-3.0, -3.0, -3.0]], dtype=F64)
    V = rotations(3, seed=4)
    A = a_from_dispersion(lam, V)
    torch.testing.assert_close(bh.dispersion(A), lam, rtol=1e-10, atol=1e-9)
    torch.testing.assert_close(bh.dt_score(A), lam.sum(-1), rtol=1e-10, atol=1e-9)
    ev = torch.linalg.eigvalsh(A)
    torch.testing.assert_close(
        bh.dt_score(A), 3 * ev[:, 0] - ev[:, 1:].sum(-1), rtol=1e-10, atol=1e-9
    )
    torch.testing.assert_close(bh.eigengap(A), -lam[:, 2], rtol=1e-10, atol=1e-9)
    q = bh.mode(A)
    assert (q[:, 3] >= 0).all()
    torch.testing.assert_close(q, a_min_eigvec(A)[1], rtol=0, atol=1e-12)
    assert torch.allclose((q * V[..., 0]).sum(-1).abs(), torch.ones(3, dtype=F64), atol=1e-10)
    D, lam_p = bh.bingham_parameters(A)
    Lambda = torch.diag_embed(torch.cat((lam_p, torch.zeros(3, 1, dtype=F64)), -1))
    torch.testing.assert_close(
        D @ Lambda @ D.mT, -A + ev[:, :1, None] * torch.eye(4, dtype=F64), rtol=0, atol=1e-9
    )
    torch.testing.assert_close(
        D.mT @ D, torch.eye(4, dtype=F64).expand(3, 4, 4), atol=1e-12, rtol=0
    )
    shift = A + 12.5 * torch.eye(4, dtype=F64)  # invariances
    torch.testing.assert_close(bh.dispersion(shift), bh.dispersion(A), rtol=0, atol=1e-9)
    torch.testing.assert_close(bh.mode(shift), q, rtol=0, atol=1e-9)


def test_section_of_a_quaternion():
    """g(q) = I - q q^T (eq. 12): dispersion (-1, -1, -1), DT score -3, mode q."""
    q = torch.nn.functional.normalize(torch.randn(5, 4, generator=gen(2), dtype=F64), dim=-1)
    A = a_from_quat(q)
    torch.testing.assert_close(bh.dispersion(A), -torch.ones(5, 3, dtype=F64), rtol=0, atol=1e-12)
    torch.testing.assert_close(bh.dt_score(A), torch.full((5,), -3.0, dtype=F64))
    torch.testing.assert_close(bh.eigengap(A), torch.ones(5, dtype=F64))
    torch.testing.assert_close(bh.mode(A), q * torch.sign(q[:, 3:]), rtol=0, atol=1e-12)


def test_bad_matrices_raise():
    A = torch.eye(4, dtype=F64).repeat(2, 3, 1, 1)
    A[1, 0, 2, 1] = float("nan")
    for fn in (bh.mode, bh.dispersion, bh.dt_score, bh.eigengap):
        with pytest.raises(ValueError, match=r"A has NaN or Inf at batch index \(1, 0\)"):
            fn(A)
    with pytest.raises(ValueError, match=r"batch index \(1, 0\)"):
        bh.nll(A, torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=F64))
    with pytest.raises(ValueError, match=r"batch index \(1, 0\)"):
        bh.sample(A, 3)
    wide = torch.diag_embed(
        torch.tensor([[0.0, 1.0, 2.0, 3.0], [0.0, 1.0, 2.0, 2 * bh.MAX_DISPERSION]])
    )
    with pytest.raises(ValueError, match=r"spread l4 - l1.*batch index \(1,\)"):
        bh.log_prob(wide, torch.tensor([0.0, 0.0, 0.0, 1.0]))
    with pytest.raises(ValueError, match="shape"):
        bh.dispersion(torch.eye(3))


# ----------------------------------------------------------------------------------- likelihood


def test_nll_matches_reference_and_invariances():
    lam = torch.tensor([[-20.0, -5.0, -1.0], [-1e4, -100.0, -0.5], [-0.1, 0.0, -2.0]], dtype=F64)
    A = a_from_dispersion(lam.sort(-1).values, rotations(3, seed=5), l1=-1.3)
    q = torch.nn.functional.normalize(torch.randn(3, 4, generator=gen(6), dtype=F64), dim=-1)
    out = bh.nll(A, q)
    ev = torch.linalg.eigvalsh(A)
    quad = torch.einsum("bi,bij,bj->b", q, A, q)
    expected = [
        quad[i].item() - ev[i, 0].item() + ref_log_n_moments(lam[i].numpy())[0] for i in range(3)
    ]
    np.testing.assert_allclose(out.numpy(), expected, rtol=1e-10, atol=1e-9)
    torch.testing.assert_close(bh.nll(A, -q), out, rtol=0, atol=1e-12)
    torch.testing.assert_close(bh.log_prob(A, q), -out, rtol=0, atol=0)
    for c in (-40.0, 3.25):
        shifted = A + c * torch.eye(4, dtype=F64)
        torch.testing.assert_close(bh.nll(shifted, q), out, rtol=0, atol=1e-9)
    # the mode is the most likely point; the density is higher there than anywhere else sampled
    assert (bh.log_prob(A, bh.mode(A)) >= bh.log_prob(A, q)).all()
    # broadcasting: (n, 4) targets against one matrix
    many = torch.nn.functional.normalize(torch.randn(7, 4, generator=gen(7), dtype=F64), dim=-1)
    batched = bh.nll(A[1], many)
    assert batched.shape == (7,)
    torch.testing.assert_close(batched[2], bh.nll(A[1], many[2]))


@pytest.mark.parametrize("spread", [1e4, 1e6, 1e7, 0.9 * bh.MAX_DISPERSION])
def test_float32_nll_of_a_sharp_belief_matches_float64(spread):
    """q^T A q and l1 are each of the size of A's entries; subtracted in float32 they left some
    1e-7 * spread nats (0.12 at 1e6, 11 at 1e8, measured before the fit term was taken in
    float64). Targets sit near the mode, where a sharp belief's targets are, and A is shifted
    by about its spread (the density does not depend on the shift)."""
    n, g = 500, gen(int(math.log10(spread)))
    frac = torch.tensor([0.0, 1e-2, 1e-1, 1.0], dtype=F64)
    lam = -(spread * frac[1:].flip(0)).expand(n, 3)  # ascending
    A = a_from_dispersion(lam, rotations(n, seed=8), l1=spread).float()
    V = torch.linalg.eigh(A.double())[1]
    angle = torch.rand(n, 1, generator=g, dtype=F64) * 3 / math.sqrt(spread * frac[1])
    off = torch.nn.functional.normalize(V[..., 1:] @ torch.randn(n, 3, 1, generator=g, dtype=F64))
    q = (V[..., 0] * angle.cos() + off.squeeze(-1) * angle.sin()).float()
    exact = bh.nll(A.double(), q.double())
    got = bh.nll(A, q)
    assert got.dtype == F32
    assert ((got.double() - exact).abs() <= 1e-3 + 1e-6 * exact.abs()).all()


def test_nll_gradient_is_finite_at_repeated_eigenvalues():
    q = torch.tensor([[0.1, -0.2, 0.3, 0.9], [0.0, 0.0, 0.0, 1.0]], dtype=F64)
    q = torch.nn.functional.normalize(q, dim=-1)
    A = (4.0 * a_from_quat(q)).requires_grad_(True)  # eigenvalues (0, 4, 4, 4)
    bh.nll(A, q).sum().backward()
    assert torch.isfinite(A.grad).all()
    # d nll / dA = q q^T - E[x x^T]; at eigenvalues (0, 4, 4, 4) E[x x^T] is known from moments
    m = bh.moments(torch.tensor([-4.0, -4.0, -4.0], dtype=F64))
    expected_second = (1 - m.sum()) * q.unsqueeze(-1) * q.unsqueeze(-2)
    expected_second = expected_second + m[0] * (
        torch.eye(4, dtype=F64) - q.unsqueeze(-1) * q.unsqueeze(-2)
    )
    expected = q.unsqueeze(-1) * q.unsqueeze(-2) - expected_second
    torch.testing.assert_close(A.grad, expected, rtol=0, atol=1e-10)


def _hopf_quadrature(n_phi: int = 64, n_angle: int = 64, dtype=F64):
    """Points and weights for the uniform probability measure on S^3 in Hopf coordinates.

    x = (sin f cos t, sin f sin t, cos f cos u, cos f sin u), d mu = sin(2f) df dt du / (2 pi)^2.
    """
    f, w = np.polynomial.legendre.leggauss(n_phi)
    f, w = (f + 1) * math.pi / 4, w * math.pi / 4
    t = (np.arange(n_angle) + 0.5) * 2 * math.pi / n_angle
    F, T, U = np.meshgrid(f, t, t, indexing="ij")
    W = (np.sin(2 * f) * w)[:, None, None] * np.ones_like(T) / n_angle**2
    x = np.stack(
        (
            np.sin(F) * np.cos(T),
            np.sin(F) * np.sin(T),
            np.cos(F) * np.cos(U),
            np.cos(F) * np.sin(U),
        ),
        -1,
    )
    return torch.tensor(x.reshape(-1, 4), dtype=dtype), torch.tensor(W.reshape(-1), dtype=dtype)


def test_log_prob_integrates_to_one_by_quadrature():
    x, w = _hopf_quadrature()
    assert abs(w.sum().item() - 1) < 1e-12
    lam = torch.tensor([[-20.0, -5.0, -1.0], [-12.0, -12.0, 0.0], [-30.0, -0.5, -0.5]], dtype=F64)
    A = a_from_dispersion(lam.sort(-1).values, rotations(3, seed=8), l1=2.0)
    total = (torch.exp(bh.log_prob(A.unsqueeze(1), x)) * w).sum(-1)
    torch.testing.assert_close(total, torch.ones(3, dtype=F64), rtol=0, atol=1e-9)
    # a wrong normaliser (e.g. the surface measure's) would be off by 2 pi^2
    surface = (torch.exp(bh.log_prob(A.unsqueeze(1), x) - bh.LOG_AREA_S3) * w).sum(-1)
    torch.testing.assert_close(surface, torch.full((3,), 0.5 / math.pi**2, dtype=F64))


def test_log_prob_integrates_to_one_by_monte_carlo_float32():
    n = 400_000
    x = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen(9)), dim=-1)
    lam = torch.tensor([[-6.0, -2.0, -1.0], [-8.0, -8.0, -0.2]])
    A = a_from_dispersion(lam, rotations(2, seed=10, dtype=F32), l1=-0.4)
    p = torch.exp(bh.log_prob(A.unsqueeze(1), x)).double()
    mean, se = p.mean(-1), p.std(-1) / math.sqrt(n)
    assert (se < 0.02).all()
    assert ((mean - 1).abs() < 5 * se).all(), (mean, se)


# ---------------------------------------------------------------------------------------- loss


def test_loss_on_the_a_head():
    head = make_head("a")
    raw = torch.randn(16, 10, generator=gen(11), dtype=F64, requires_grad=True)
    pred = head(raw)
    q = torch.nn.functional.normalize(torch.randn(16, 4, generator=gen(12), dtype=F64), dim=-1)
    loss = BinghamNLLLoss(rep="a")(pred, {"q": q, "R": pred.R.detach()})
    assert loss.shape == ()
    torch.testing.assert_close(loss, bh.nll(pred.A, q).mean())
    loss.backward()
    assert torch.isfinite(raw.grad).all() and raw.grad.abs().sum() > 0
    # without "q" the targets come from "R"; either sign of q gives the same loss
    from_r = BinghamNLLLoss()(pred, {"R": quat_to_rotmat(-q)})
    torch.testing.assert_close(from_r, loss, rtol=0, atol=1e-12)


@pytest.mark.parametrize("rep", ["quat", "sixd", "svd9d"])
def test_loss_refuses_heads_without_a_belief(rep):
    pred = make_head(rep)(torch.randn(3, make_head(rep).out_dim, generator=gen(13)))
    message = (
        f"loss=bingham needs a head that defines a belief (rep=a or rep=fisher); rep={rep} does not"
    )
    with pytest.raises(ValueError) as info:
        BinghamNLLLoss()(pred, {"q": pred.q})
    assert str(info.value) == message
    with pytest.raises(ConfigError) as info:
        BinghamNLLLoss(rep=rep)
    assert info.value.key == "rep" and info.value.message == message


# ------------------------------------------------------------------------------------- sampling


def test_sample_second_moments_match_the_normaliser_gradient():
    """E[(v_i^T x)^2] from 300k draws vs d log N / d lam within 5 standard errors (fixed seed).

    The same statistic for a Bingham 5% more or less concentrated is rejected by > 10 standard
    errors, so the test has the power to fail.
    """
    n = 300_000
    lam = torch.tensor([[-20.0, -5.0, -1.0], [-1e4, -100.0, -0.5], [-3.0, -3.0, -0.0]], dtype=F64)
    V = rotations(3, seed=14)
    x = bh.sample(a_from_dispersion(lam, V, l1=5.0), n, generator=gen(15))
    assert x.shape == (3, n, 4)
    torch.testing.assert_close(x.norm(dim=-1), torch.ones(3, n, dtype=F64))
    y = torch.einsum("bji,bnj->bni", V, x)  # coordinates in the eigenbasis (v1, v2, v3, v4)
    coeffs = torch.cat((torch.zeros(3, 1, dtype=F64), lam.flip(-1)), -1)  # for (v1, v2, v3, v4)
    y2 = y * y
    mean, se = y2.mean(1), y2.std(1) / math.sqrt(n)
    z = (mean - bh.moments(coeffs)) / se
    assert z.abs().max() < 5, z
    for factor in (0.95, 1.05):
        z_wrong = (mean - bh.moments(coeffs * factor)) / se
        assert (z_wrong.abs().amax(-1) > 10).all(), z_wrong  # every row
    cross = y[..., :, None] * y[..., None, :]
    off = torch.triu_indices(4, 4, 1)
    cross = cross[..., off[0], off[1]]
    z_off = cross.mean(1) / (cross.std(1) / math.sqrt(n))
    assert z_off.abs().max() < 5, z_off


def test_sample_shapes_devices_and_reproducibility():
    A = a_from_dispersion(
        -torch.rand(2, 3, 3, generator=gen(16), dtype=F32) * 50,
        rotations(6, 17, F32).reshape(2, 3, 4, 4),
    )
    x1 = bh.sample(A, 11, generator=gen(18))
    x2 = bh.sample(A, 11, generator=gen(18))
    assert x1.shape == (2, 3, 11, 4) and x1.dtype == F32
    torch.testing.assert_close(x1, x2, rtol=0, atol=0)
    assert bh.sample(A, 0).shape == (2, 3, 0, 4)
    assert bh.sample(A[:0], 5).shape == (0, 3, 5, 4)
    with pytest.raises(ValueError, match="n must be"):
        bh.sample(A, -1)


@pytest.mark.parametrize("reduced", [torch.bfloat16, torch.float16])
def test_sample_and_what_draws_on_it_are_unchanged_under_autocast(reduced):
    """Autocast (CPU: bfloat16 or float16) lowers matrix products: a sharp belief's samples were
    rotated into place in bfloat16, 3.6 deg off its mode instead of 0.1 deg, and the HPD levels
    and credible radius drawn on them were wrong. They run in float32 (`float32_under_autocast`),
    as every public function does."""
    A = 1e6 * a_from_quat(torch.nn.functional.normalize(torch.tensor([0.3, -0.2, 0.5, 0.7]), dim=0))
    x = bh.sample(A, 2000, generator=gen(3))
    level = bh.hpd_level(A, x[:5], 500, generator=gen(4))
    radius = bh.credible_radius_deg(A, 0.9, 1024, generator=gen(5))
    with torch.autocast("cpu", dtype=reduced):
        assert bh.sample(A, 2000, generator=gen(3)).dtype == F32
        torch.testing.assert_close(bh.sample(A, 2000, generator=gen(3)), x, rtol=0, atol=1e-6)
        torch.testing.assert_close(bh.hpd_level(A, x[:5], 500, generator=gen(4)), level)
        torch.testing.assert_close(bh.credible_radius_deg(A, 0.9, 1024, generator=gen(5)), radius)


def test_sample_round_cap(monkeypatch):
    monkeypatch.setattr(bh.sampling, "_round_size", lambda remaining, rate: 1)
    A = torch.diag(torch.tensor([0.0, 1.0, 2.0, 3.0]))
    with pytest.raises(RuntimeError, match="did not produce 50 samples in 3 rounds"):
        bh.sample(A, 50, max_rounds=3)


def test_mode_has_a_finite_gradient_where_the_two_smallest_eigenvalues_meet():
    """The mode comes from the A head's solver: at l1 == l2 its gradient stays finite (eigh's is
    NaN there), and it equals the head's quaternion."""
    A = torch.diag(torch.tensor([1.0, 1.0, 2.0, 3.0], dtype=torch.float64)).requires_grad_(True)
    bh.mode(A).sum().backward()
    assert torch.isfinite(A.grad).all()
    B = torch.randn(7, 4, 4, dtype=torch.float64)
    B = B + B.mT
    torch.testing.assert_close(bh.mode(B), a_min_eigvec(B)[1])


def test_a_prediction_carries_the_uncertainty_of_its_belief():
    """dispersion, dt and eigengap of a prediction are the Bingham module's, defined once."""
    head = make_head("a")
    prediction = head(torch.randn(5, 10, dtype=torch.float64))
    torch.testing.assert_close(prediction.dispersion, bh.dispersion(prediction.A))
    torch.testing.assert_close(prediction.dt, bh.dt_score(prediction.A))
    torch.testing.assert_close(prediction.eigengap, bh.eigengap(prediction.A))
    assert (prediction.dt <= 0).all() and (prediction.eigengap >= 0).all()
    plain = make_head("sixd")(torch.randn(5, 6))
    assert plain.dispersion is None and plain.dt is None and plain.eigengap is None


@pytest.mark.parametrize("name", ["log_prob", "nll"])
def test_a_float32_and_a_float64_argument_give_the_float64_result(name):
    """A and q promote as torch's elementwise ops do (a matmul would refuse the pair)."""
    g = torch.Generator().manual_seed(3)
    A = torch.randn(6, 4, 4, generator=g, dtype=torch.float64)
    A = (A + A.transpose(-1, -2)).float().double()  # values float32 holds exactly
    q = torch.nn.functional.normalize(torch.randn(6, 4, generator=g, dtype=torch.float64), dim=-1)
    q = q.float().double()
    function = getattr(bh, name)
    for got in (function(A.float(), q), function(A, q.float())):
        assert got.dtype == torch.float64
        torch.testing.assert_close(got, function(A, q), rtol=0, atol=0)
