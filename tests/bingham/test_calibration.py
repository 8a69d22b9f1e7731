"""Calibration of a Bingham belief: HPD levels, coverage and the ECE (rotlearn.bingham.calibration).

The statistical tests rest on an exact fact, not on a seed: where a target and the n draws of
`hpd_level` are i.i.d. from the same belief, the estimated level K / n is exactly uniform on
{0, 1/n, ..., 1} (the target's rank among n + 1 draws), whatever the belief. So over M targets the
empirical CDF of the levels is that of a discrete uniform law, and by the Dvoretzky-Kiefer-Wolfowitz
inequality it stays within eps of it everywhere with probability >= 1 - 2 exp(-2 M eps^2). With
M = 4000 and eps = 0.04 (5.1 times the largest standard deviation 1 / (2 sqrt(M)) of one coverage)
a correct implementation fails with probability below 6e-6.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from rotlearn import bingham as bh
from rotlearn.bingham import credible_radius_deg
from tests.conftest import DTYPES, gen

F32, F64 = torch.float32, torch.float64
M, N = 4000, 200  # targets, draws per belief
EPS = 0.04  # the DKW bound: 2 exp(-2 M EPS^2) = 5.5e-6
PROPS = settings(max_examples=25, deadline=None)


def beliefs(
    seed: int, m: int, dtype: torch.dtype = F64, offset: float = 0.0, scales: tuple = (-1, 3)
) -> torch.Tensor:
    """(m, 4, 4) random beliefs from near-uniform (eigenvalue spread ~0.1) to concentrated (~1e4,
    a few degrees; `scales`: the range of log10 of the scale), with random directions, shifted by
    `offset` I (the same belief)."""
    g = gen(seed)
    B = torch.randn(m, 4, 4, generator=g, dtype=F64)
    scale = torch.logspace(*scales, m, dtype=F64)[torch.randperm(m, generator=g)]
    A = B @ B.mT * scale[:, None, None] + offset * torch.eye(4, dtype=F64)
    return A.to(dtype)


def unit_quats(seed: int, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
    q = torch.randn(*shape, 4, generator=gen(seed), dtype=dtype)
    return q / q.norm(dim=-1, keepdim=True)


def discrete_uniform_gap(levels: torch.Tensor, n: int) -> float:
    """sup_k |P_emp(level <= k/n) - (k + 1)/(n + 1)|: the KS distance of the levels from the law
    of a calibrated belief's estimated levels (at its jumps, where the supremum is attained)."""
    k = torch.arange(n + 1, dtype=F64)
    empirical = (levels.double().reshape(-1, 1) <= k / n + 1e-9).double().mean(0)
    return float((empirical - (k + 1) / (n + 1)).abs().max())


@pytest.mark.parametrize(
    ("dtype", "offset", "scales"),
    [(F64, 0.0, (-1, 3)), (F32, -300.0, (-1, 3)), (F32, 1e6, (5, 6.5))],
    ids=["float64", "float32", "float32-sharp"],  # sharp: spreads ~1e5-1e7 (~0.01-0.1 degree)
)
def test_targets_drawn_from_the_belief_give_uniform_levels_and_no_calibration_error(
    dtype, offset, scales
):
    A = beliefs(0, M, dtype, offset, scales)
    q = bh.sample(A, 1, gen(1))[:, 0]
    levels = bh.hpd_level(A, q, N, gen(2))
    assert levels.shape == (M,) and levels.dtype == dtype
    assert discrete_uniform_gap(levels, N) <= EPS
    alphas = torch.tensor(bh.CREDIBLE_LEVELS, dtype=F64)
    assert bh.coverage(levels).sub(alphas).abs().max() <= EPS + 1 / (N + 1)
    assert bh.expected_calibration_error(levels) <= EPS + 1 / (N + 1)


def test_a_belief_too_sharp_for_its_targets_undercovers_and_the_ece_says_so():
    # targets from A / 3 (a belief three times wider): the HPD regions of A hold fewer of them.
    # Measured ECE 0.26 at M = 4000; a calibrated belief stays below EPS + 1/(N+1) = 0.045 (above)
    A = beliefs(3, M)
    levels = bh.hpd_level(A, bh.sample(A / 3, 1, gen(4))[:, 0], N, gen(5))
    alphas = torch.tensor(bh.CREDIBLE_LEVELS, dtype=F64)
    assert (bh.coverage(levels) < alphas - EPS).all()
    assert bh.expected_calibration_error(levels) > 0.15


@pytest.mark.parametrize(
    ("dtype", "offset", "scales"),
    [(F64, 0.0, (-1, 3)), (F32, 1e6, (5, 6.5))],
    ids=["float64", "float32-sharp"],  # sharp: the energies of float32 draws need float64 sums
)
def test_the_mode_is_inside_every_credible_region(dtype, offset, scales):
    A = beliefs(6, 200, dtype, offset, scales)
    levels = bh.hpd_level(A, bh.mode(A), 100, gen(7))
    assert levels.max() <= 0.01  # 0 up to the rounding of the mode's quadratic form
    assert bh.coverage(levels).min() == 1.0
    expected = sum(1 - a for a in bh.CREDIBLE_LEVELS) / 9  # 0.5: the ECE of a belief far too wide
    assert bh.expected_calibration_error(levels) >= expected - 0.01


@pytest.mark.parametrize("dtype", [F32, F64])
def test_an_isotropic_belief_puts_every_target_at_the_middle_level(dtype):
    """A = cI (a network's all-zero output) gives every draw the target's energy: the strict
    count gave every target level 0, as if the truth were the belief's mode. A draw of the same
    energy counts half: level 1/2."""
    A = (2.0 * torch.eye(4, dtype=dtype)).expand(50, 4, 4)
    q = torch.nn.functional.normalize(torch.randn(50, 4, generator=gen(8), dtype=dtype), dim=-1)
    assert torch.equal(bh.hpd_level(A, q, 64, gen(9)), torch.full((50,), 0.5, dtype=dtype))


@PROPS
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 64), dtype=st.sampled_from([F32, F64]))
def test_levels_are_fractions_of_the_draws_and_grow_with_the_quadratic_form(seed, n, dtype):
    A = beliefs(seed, 1, dtype)[0] * 10.0
    q = unit_quats(seed + 1, (6,), dtype)
    # one call per target with the same seed: every target is compared with the same draws
    levels = torch.stack([bh.hpd_level(A, qi, n, gen(seed + 2)) for qi in q])
    assert ((levels >= 0) & (levels <= 1)).all()
    torch.testing.assert_close(levels * n, (levels * n).round(), rtol=0, atol=1e-4)
    form = torch.einsum("bi,ij,bj->b", q.double(), A.double(), q.double())
    order = torch.argsort(form)
    assert (levels[order].diff() >= 0).all()
    # the density is antipodally symmetric: -q is the same rotation, at the same level
    torch.testing.assert_close(torch.stack([bh.hpd_level(A, -qi, n, gen(seed + 2)) for qi in q]),
                               levels, rtol=0, atol=0)  # fmt: skip


@pytest.mark.parametrize("dtype", [F32, F64])
@pytest.mark.parametrize(
    ("a_shape", "q_shape", "out"),
    [((), (), ()), ((2, 3), (2, 3), (2, 3)), ((), (5,), (5,)), ((4, 1), (3,), (4, 3)),
     ((0,), (0,), (0,))],
)  # fmt: skip
def test_any_batch_shape_broadcast_between_beliefs_and_targets(dtype, a_shape, q_shape, out):
    A = beliefs(8, max(math.prod(a_shape), 1), dtype)[: math.prod(a_shape)].reshape(*a_shape, 4, 4)
    q = unit_quats(9, q_shape, dtype)
    levels = bh.hpd_level(A, q, 16, gen(10))
    assert levels.shape == out and levels.dtype == dtype
    assert ((levels >= 0) & (levels <= 1)).all()


def test_coverage_and_ece_of_known_levels():
    levels = torch.tensor([0.05, 0.1, 0.15, 0.5, 0.95], dtype=F32)
    cover = bh.coverage(levels, (0.1, 0.5, 1.0))
    torch.testing.assert_close(cover, torch.tensor([0.4, 0.8, 1.0], dtype=F64))
    ece = bh.expected_calibration_error(levels, (0.1, 0.5, 1.0))
    torch.testing.assert_close(ece, torch.tensor((0.3 + 0.3 + 0.0) / 3, dtype=F64))
    assert bh.CREDIBLE_LEVELS == (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
    assert bh.coverage(levels.reshape(5, 1)).shape == (9,)
    # a level of k / n draws in float32 counts as inside the region of the same level
    assert bh.coverage(torch.tensor([100 / 1000], dtype=F32), (0.1,)) == 1.0


def test_bad_input_is_named():
    A, q = beliefs(11, 2), torch.tensor([[0.0, 0.0, 0.0, 1.0]] * 2, dtype=F64)
    with pytest.raises(ValueError, match="num_samples"):
        bh.hpd_level(A, q, 0)
    with pytest.raises(ValueError, match=r"q: expected a tensor of shape \(\.\.\., 4\)"):
        bh.hpd_level(A, q[:, :3], 8)
    with pytest.raises(ValueError, match=r"q has NaN or Inf at batch index \(1,\)"):
        bh.hpd_level(A, torch.stack([q[0], torch.full((4,), math.nan, dtype=F64)]), 8)
    with pytest.raises(ValueError, match="A has NaN"):
        bh.hpd_level(torch.full((4, 4), math.inf, dtype=F64), q[0], 8)
    with pytest.raises(ValueError, match="no levels"):
        bh.coverage(torch.empty(0))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        bh.coverage(torch.zeros(3), (0.5, 1.5))


# -- recalibrating the credible levels (Kuleshov et al. 2018) ----------------------------------


def test_a_level_map_fitted_on_held_out_targets_makes_new_levels_uniform():
    """Targets from beliefs 3 times wider than the predicted ones, in a mixture with targets from
    the beliefs themselves (a shape no temperature fixes): the levels are far from uniform, and
    the map fitted on one half makes the other half's levels uniform. Both halves are i.i.d., so
    each half's empirical CDF is within EPS_HALF of the common law (DKW, 2 exp(-2 (M/2) eps^2) =
    1e-4 each), and the mapped levels are uniform up to 2 EPS_HALF plus the knots' resolution."""
    A = beliefs(11, M)
    g = gen(12)
    wide = torch.rand(M, generator=g, dtype=F64) < 0.5
    scale = torch.where(wide, 1.0 / 3.0, 1.0)[:, None, None]
    q = bh.sample(A * scale, 1, generator=g)[:, 0]
    levels = bh.hpd_level(A, q, N, generator=gen(13))
    fit, held_out = levels[: M // 2], levels[M // 2 :]
    assert bh.expected_calibration_error(held_out) > 0.1  # the control: uncalibrated
    level_map = bh.fit_level_map(fit)
    mapped = level_map(held_out)
    eps_half = math.sqrt(math.log(2 / 1e-4) / M)  # 0.05: DKW at M / 2 samples
    grid = torch.tensor(bh.CREDIBLE_LEVELS, dtype=F64)
    assert (bh.coverage(mapped) - grid).abs().max() < 2 * eps_half
    assert float(bh.expected_calibration_error(mapped)) < 2 * eps_half


def test_a_level_map_is_monotone_and_its_mass_inverts_it():
    level_map = bh.fit_level_map(torch.rand(500, generator=gen(0), dtype=F64).square())
    masses = level_map.masses
    assert masses[0] == 0 and masses[-1] == 1 and bool((masses.diff() >= 0).all())
    u = torch.linspace(0, 1, 101, dtype=F64)
    assert bool((level_map(u).diff() >= 0).all())
    alphas = torch.tensor(bh.CREDIBLE_LEVELS, dtype=F64)
    torch.testing.assert_close(level_map(level_map.mass(alphas)), alphas)
    # the identity map leaves levels as they are
    identity = bh.LevelMap(torch.linspace(0, 1, 21, dtype=F64))
    torch.testing.assert_close(identity(u), u)


@pytest.mark.parametrize(
    "masses", [[0.0], [0.1, 1.0], [0.0, 0.9], [0.0, 0.6, 0.5, 1.0], [0.0, math.nan, 1.0]]
)
def test_a_level_map_refuses_masses_that_are_no_distribution(masses):
    with pytest.raises(ValueError, match="masses"):
        bh.LevelMap(torch.tensor(masses, dtype=F64))


def test_fit_level_map_refuses_no_levels_and_levels_outside_0_1():
    with pytest.raises(ValueError, match="no levels"):
        bh.fit_level_map(torch.empty(0))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        bh.fit_level_map(torch.tensor([0.5, 1.5]))


@pytest.mark.parametrize("dtype", DTYPES)
def test_credible_radius_matches_the_closed_forms_of_the_uniform_and_a_sharp_belief(dtype):
    """Uniform on SO(3) (A = 0): the angle has CDF (t - sin t) / pi, so the 90 % radius solves
    t - sin t = 0.9 pi (171.3 deg). Isotropic and sharp, A = s (I - m m^T): the quaternion's
    offset from m is nearly N(0, I_3 / (2 s)) and the angle 2 |offset|, so the radius is
    2 sqrt(chi2_3(0.9) / (2 s)) (chi2_3(0.9) = 6.2514) to O(1 / s)."""
    from scipy.optimize import brentq

    uniform = brentq(lambda t: t - math.sin(t) - 0.9 * math.pi, 0.0, math.pi)
    m = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, 0.5, 0.8], dtype=dtype), dim=0)
    s = 1e4
    A = torch.stack([torch.zeros(4, 4, dtype=dtype),
                     s * (torch.eye(4, dtype=dtype) - torch.outer(m, m))])  # fmt: skip
    radius = credible_radius_deg(A, 0.9, num_samples=40000, generator=gen(3))
    assert radius.dtype == dtype and radius.shape == (2,)
    # 40000 draws: the mass inside the estimate is 0.9 +- 0.0015; in angle, within ~0.5 %
    assert float(radius[0]) == pytest.approx(math.degrees(uniform), rel=5e-3)
    sharp = math.degrees(2 * math.sqrt(6.2514 / (2 * s)))
    assert float(radius[1]) == pytest.approx(sharp, rel=1e-2)


def test_credible_radius_grows_with_the_level_and_takes_any_batch_shape():
    A = 50.0 * (torch.eye(4, dtype=torch.float64) - torch.diag(torch.tensor([0.0, 0, 0, 1.0])))
    A = A.expand(2, 3, 4, 4)
    low, high = (credible_radius_deg(A, level, 2000, gen(0)) for level in (0.5, 0.9))
    assert low.shape == high.shape == (2, 3) and bool((low < high).all())
    with pytest.raises(ValueError, match="level"):
        credible_radius_deg(A, 0.0)
