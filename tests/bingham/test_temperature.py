"""Post-hoc temperature scaling (`rotlearn.bingham.temperature`): recovery, convexity, symmetry."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from rotlearn import bingham as bh
from tests.conftest import gen

F64 = torch.float64


def beliefs(n: int, seed: int, low: float = 2.0, high: float = 60.0) -> torch.Tensor:
    """n random Bingham matrices (n, 4, 4): eigenvalues 0 <= a <= b <= c with a, b, c uniform in
    [low, high], on Haar-random eigenvectors."""
    g = gen(seed)
    V = torch.linalg.qr(torch.randn(n, 4, 4, generator=g, dtype=F64))[0]
    spread = (low + (high - low) * torch.rand(n, 3, generator=g, dtype=F64)).sort(-1).values
    ev = torch.cat((torch.zeros(n, 1, dtype=F64), spread), -1)
    return V @ torch.diag_embed(ev) @ V.mT


def targets(A: torch.Tensor, seed: int) -> torch.Tensor:
    """One quaternion drawn from each belief A (n, 4, 4): (n, 4)."""
    return bh.sample(A, 1, generator=gen(seed)).squeeze(-2)


def fisher_information(A: torch.Tensor, beta: float, h: float = 1e-5) -> float:
    """Sum over the samples of Var_beta(q^T A q): the information about beta that n targets drawn
    from the beliefs beta A carry (minus the derivative of the expected energy
    E_beta[e] = -lam . m(beta lam), by central differences)."""
    lam = bh.dispersion(A)

    def expected_energy(b: float) -> torch.Tensor:
        return -(lam * bh.moments(b * lam)).sum(-1)

    return float(-(expected_energy(beta * (1 + h)) - expected_energy(beta * (1 - h))).sum()) / (
        2 * beta * h
    )


@pytest.mark.parametrize("t0", [0.5, 1.0, 3.0])
def test_fit_recovers_a_known_temperature_within_its_standard_error(t0):
    n = 3000
    A = beliefs(n, seed=11)
    q = targets(A / t0, seed=12)
    fit = bh.fit_temperature(A, q)
    assert fit.num == n and fit.at_bound is None
    # the MLE of beta = 1 / T is asymptotically normal with variance 1 / (Fisher information)
    beta0, beta = 1.0 / t0, 1.0 / float(fit.temperature)
    se = 1.0 / math.sqrt(fisher_information(A, beta0))
    assert abs(beta - beta0) < 5.0 * se, (beta, beta0, se)
    assert se / beta0 < 0.05  # the test has the power to tell 0.5, 1 and 3 apart
    # the fitted temperature is never worse than the true one, nor than no temperature
    true_nll = float(bh.nll(A / t0, q).mean())
    assert fit.nll_after <= true_nll + 1e-12
    assert fit.nll_after <= fit.nll_before + 1e-12
    assert fit.nll_before == pytest.approx(float(bh.nll(A, q).mean()), rel=1e-10)
    assert fit.nll_after == pytest.approx(float(bh.nll(A / fit.temperature, q).mean()), rel=1e-10)


def test_mean_nll_is_convex_in_beta_and_minimal_at_the_fit():
    A = beliefs(400, seed=21)
    q = targets(A / 2.0, seed=22)
    t = bh.fit_temperature(A, q).temperature
    betas = torch.logspace(-2, 1, 31, dtype=F64).tolist()
    values = torch.tensor([float(bh.nll(A * b, q).mean()) for b in betas], dtype=F64)
    b = torch.tensor(betas, dtype=F64)
    # convexity on the uneven grid: every chord lies above the curve
    left, mid, right = b[:-2], b[1:-1], b[2:]
    w = (mid - left) / (right - left)
    chord = (1 - w) * values[:-2] + w * values[2:]
    assert (values[1:-1] <= chord + 1e-9).all()
    best = float(bh.nll(A / t, q).mean())
    assert best <= values.min() + 1e-12
    for factor in (0.99, 1.01):  # a local minimum, so the global one (convexity)
        assert best < float(bh.nll(A / (t * factor), q).mean())


@settings(max_examples=15, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    scale=st.floats(0.05, 20.0),
    shift=st.floats(-50.0, 50.0),
    t0=st.floats(0.3, 4.0),
)
def test_temperature_scales_with_a_and_ignores_shifts_and_signs(seed, scale, shift, t0):
    A = beliefs(24, seed=seed)
    q = targets(A / t0, seed=seed + 1)
    t = float(bh.fit_temperature(A, q).temperature)
    assert t > 0
    assert float(bh.fit_temperature(scale * A, q).temperature) == pytest.approx(scale * t, rel=1e-7)
    eye = torch.eye(4, dtype=F64)
    assert float(bh.fit_temperature(A + shift * eye, -q).temperature) == pytest.approx(t, rel=1e-7)
    # float32 input gives the same answer (computed in float64), in float32
    t32 = bh.fit_temperature(A.float(), q.float()).temperature
    assert t32.dtype == torch.float32 and t32.dim() == 0
    assert float(t32) == pytest.approx(t, rel=1e-4)


def test_broadcasting_and_batch_shapes():
    A = beliefs(6, seed=31)
    q = targets(A, seed=32)
    flat = bh.fit_temperature(A, q).temperature
    torch.testing.assert_close(
        bh.fit_temperature(A.reshape(2, 3, 4, 4), q.reshape(2, 3, 4)).temperature, flat
    )
    many = bh.sample(A[0], 50, generator=gen(33))  # (50, 4) targets of one belief
    assert bh.fit_temperature(A[0], many).num == 50


def test_the_bracket_keeps_every_tempered_belief_supported():
    A = beliefs(5, seed=41)
    modes = bh.mode(A)
    fit = bh.fit_temperature(A, modes)  # every target at its mode: sharper is always better
    assert fit.at_bound == "lower"
    spread = float(bh.dispersion(A)[:, 0].neg().max())
    assert spread / float(fit.temperature) <= bh.MAX_DISPERSION
    assert math.isfinite(fit.nll_after)
    bh.nll(A / fit.temperature, modes)  # still inside the supported range: no error
    # targets farthest from the modes: the belief is anti-informative, T goes to the flat end
    _, V = torch.linalg.eigh(A)
    worst = bh.fit_temperature(A, V[..., -1])
    assert worst.at_bound == "upper" and worst.nll_after < 1e-4


def test_spreads_beyond_max_dispersion_fit_with_an_unknown_before():
    scale = 0.1 * bh.MAX_DISPERSION
    A = beliefs(50, seed=51) * scale  # spreads up to 6 MAX_DISPERSION
    q = targets(A / scale, seed=52)
    fit = bh.fit_temperature(A, q)
    assert math.isnan(fit.nll_before) and math.isfinite(fit.nll_after)
    assert float(fit.temperature) == pytest.approx(scale, rel=0.2)


@pytest.mark.parametrize(
    ("A", "q", "error", "message"),
    [
        (torch.zeros(0, 4, 4), torch.zeros(0, 4), ValueError, "no samples"),
        (torch.eye(4).expand(3, 4, 4), torch.eye(4)[:3], ValueError, "multiple of the identity"),
        (torch.eye(4).expand(2, 4, 4), torch.zeros(3, 4), ValueError, "do not broadcast"),
        (torch.eye(4), torch.zeros(3), ValueError, r"q: expected a tensor of shape \(\.\.\., 4\)"),
        (torch.eye(4, dtype=torch.long), torch.zeros(4), TypeError, "A must be a floating"),
    ],
)
def test_bad_input_is_refused_with_a_reason(A, q, error, message):
    with pytest.raises(error, match=message):
        bh.fit_temperature(A, q)


def test_non_finite_input_names_the_first_bad_sample():
    A = beliefs(4, seed=61)
    q = targets(A, seed=62)
    bad = A.clone()
    bad[2, 0, 1] = math.nan
    with pytest.raises(ValueError, match=r"A has NaN or Inf at batch index \(2,\)"):
        bh.fit_temperature(bad, q)
    bad_q = q.clone()
    bad_q[3, 0] = math.inf
    with pytest.raises(ValueError, match=r"q has NaN or Inf at batch index \(3,\)"):
        bh.fit_temperature(A, bad_q)
    with pytest.raises(ValueError, match="rtol"):
        bh.fit_temperature(A, q, rtol=0.0)
