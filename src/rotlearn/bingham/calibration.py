"""Is a Bingham belief calibrated? Highest-density credible regions, their coverage, the ECE.

Quaternions are scalar LAST, (x, y, z, w); the belief is p(x) ~ exp(-x^T A x) over unit
quaternions (paper eqs. 14-15; `rotlearn.bingham`).

Definitions
-----------
The level-alpha highest-posterior-density (HPD) credible region of the belief A is

    C_alpha = {x : p(x; A) >= c_alpha} = {x : x^T A x <= t_alpha},

with c_alpha (t_alpha) chosen so that the belief gives C_alpha the mass alpha. Among all regions of
mass alpha it has the smallest volume. The density is taken w.r.t. the uniform probability measure
on S^3 (the package's measure, the Haar measure of SO(3) under q -> R(q)); p is antipodally
symmetric, so C_alpha is also a region of SO(3), of Haar volume as small as mass alpha allows.

`hpd_level(A, q)` is the mass of the HPD region whose boundary passes through q,

    level(q) = P_{x ~ A}[x^T A x < q^T A q],

so q lies inside C_alpha iff level(q) <= alpha. For a calibrated belief (the targets q are drawn
from the predicted beliefs themselves) level(q) is uniform on [0, 1]: the fraction of targets
inside C_alpha, `coverage`, is alpha at every level, and the expected calibration error
`expected_calibration_error` = mean over levels |coverage(alpha) - alpha| is 0. A belief too sharp
(over-confident) covers less than alpha; one too wide covers more.

For a person, the belief's spread in degrees: `credible_radius_deg`, the radius r of the
smallest geodesic ball around the mode (the predicted rotation) that holds a given mass,
P_{x ~ A}[angle(x, mode) <= r] = level, with angle(x, m) = 2 atan2(|x - (x.m) m|, |x.m|) the
angle of the rotation between the two (either sign of x). "90 % of the belief lies within r
degrees of the prediction." (The HPD region of the same mass is smaller where the belief is not
isotropic; the ball is what a single number can say.)

Monte Carlo
-----------
No closed form of the mass of {x^T A x <= t} is used: `hpd_level` estimates it from n = num_samples
draws of the belief itself (`rotlearn.bingham.sample`), as the fraction K / n of draws below q's
quadratic form. K ~ Binomial(n, level(q)), so the estimate is unbiased with standard deviation
sqrt(level (1 - level) / n) <= 1 / (2 sqrt(n)) (0.016 for n = 1000). Where q is itself drawn from
the belief, K / n is EXACTLY uniform on {0, 1/n, ..., 1} (q's rank among n + 1 i.i.d. draws), so
the expected coverage at alpha is (floor(n alpha) + 1) / (n + 1): at most 1 / (n + 1) above alpha.
Over M targets a coverage is a binomial proportion, of standard deviation <= 1 / (2 sqrt(M)); by the
Dvoretzky-Kiefer-Wolfowitz inequality every coverage is within eps of its expectation with
probability >= 1 - 2 exp(-2 M eps^2).

Recalibrating the credible levels
---------------------------------
A temperature (`rotlearn.bingham.fit_temperature`) fixes the belief's overall scale, not its
shape: where the errors are heavier-tailed than the Bingham belief (more targets both near the
mode and far out than the belief says), coverage(alpha) stays above alpha for small alpha and
below it for large alpha at every temperature. `fit_level_map` fits the monotone map of credible
levels that makes them uniform on held-out (validation) targets, the recalibration of Kuleshov
et al. (ICML 2018) for HPD levels: the calibrated level of q is R(level(q)), R the empirical
distribution function of the validation levels, read at K + 1 quantile knots and linear between
them. The regions stay the belief's own HPD regions; only their labels change: the calibrated
level-alpha region is the belief's HPD region of mass R^{-1}(alpha) (`LevelMap.mass`). The mode,
the density's ranking of rotations (and so DT's ranking of samples) and the NLL are unchanged.
On new data from the validation distribution the calibrated levels are uniform up to the
sampling error of the validation set (about 0.35 / sqrt(n_val) in the ECE).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from rotlearn.bingham.descriptors import _check_A, _check_q, _symmetric, mode
from rotlearn.bingham.sampling import sample
from rotlearn.geometry import linalg

__all__ = [
    "CREDIBLE_LEVELS",
    "LevelMap",
    "coverage",
    "credible_radius_deg",
    "expected_calibration_error",
    "fit_level_map",
    "hpd_level",
]

CREDIBLE_LEVELS: tuple[float, ...] = tuple(round(0.1 * i, 1) for i in range(1, 10))
"""The credible levels alpha = 0.1, 0.2, ..., 0.9 of the coverage and the ECE."""

_CHUNK_SAMPLES = 1 << 18  # belief draws per chunk (the sampler's proposals are ~2x that, x 4)


def hpd_level(
    A: Tensor, q: Tensor, num_samples: int, generator: torch.Generator | None = None
) -> Tensor:
    """The belief mass of the HPD region whose boundary passes through q (module docstring).

    Estimated from `num_samples` draws of each belief: the fraction of draws x with
    x^T A x < q^T A q, a draw of the same energy counting half (an isotropic belief, A = cI,
    gives every draw the target's energy: level 1/2, not 0); standard deviation
    <= 1 / (2 sqrt(num_samples)). Computed with A shifted to A - l1 I (same regions) so that
    concentrated beliefs keep their precision in float32.

    Args:
        A: (..., 4, 4) symmetric matrices (their symmetric part is used), finite.
        q: (..., 4) unit quaternions (x, y, z, w), batch shape broadcast against A's (each
            broadcast pair gets its own draws).
        num_samples: draws per belief, >= 1.
        generator: random source on A's device (None: torch's default).

    Returns:
        (...,) levels in [0, 1] (multiples of 1 / (2 num_samples)), in the promoted dtype of A and q
        (float32 for lower precisions); q inside the level-alpha region iff level <= alpha.
        Not differentiable.
    """
    _check_A(A)
    _check_q(q)
    if num_samples < 1:
        raise ValueError(f"num_samples must be >= 1, got {num_samples}")
    dtype = torch.promote_types(A.dtype, q.dtype)
    dtype = dtype if dtype in (torch.float32, torch.float64) else torch.float32
    batch = torch.broadcast_shapes(A.shape[:-2], q.shape[:-1])
    with torch.no_grad():
        A = _symmetric(A).to(dtype).expand(*batch, 4, 4).reshape(-1, 4, 4)
        q = q.to(dtype).expand(*batch, 4).reshape(-1, 4)
        # The energies x^T (A - l1 I) x in float64: in float32 they would carry rounding of
        # about 1e-7 (l4 - l1), as much as a sharp belief's energies themselves.
        A64 = A.double()
        S = A64 - linalg.eigvalsh(A64)[:, :1, None] * torch.eye(4, dtype=A64.dtype, device=A.device)
        target = torch.einsum("bi,bij,bj->b", q.double(), S, q.double())
        levels = torch.empty_like(target, dtype=dtype)
        rows = max(1, _CHUNK_SAMPLES // num_samples)
        for start in range(0, A.shape[0], rows):
            part = slice(start, start + rows)
            x = sample(A[part], num_samples, generator)  # (rows, n, 4)
            s = torch.einsum("bni,bij,bnj->bn", x.double(), S[part], x.double())
            t = target[part].unsqueeze(-1)  # a draw of the same energy counts half (mid-rank)
            below = (s < t).sum(-1) + 0.5 * (s == t).sum(-1)
            levels[part] = below.to(dtype) / num_samples
    return levels.reshape(batch)


def coverage(levels: Tensor, alphas: tuple[float, ...] = CREDIBLE_LEVELS) -> Tensor:
    """The fraction of targets inside the level-alpha HPD region, for each alpha.

    Args:
        levels: (...) `hpd_level`s of the targets (any shape; all are pooled), at least one.
        alphas: the credible levels, each in [0, 1].

    Returns:
        (len(alphas),) fractions mean(level <= alpha), float64, on levels' device.
    """
    if levels.numel() == 0:
        raise ValueError("coverage of no levels: at least one target is needed")
    if not all(0.0 <= a <= 1.0 for a in alphas):
        raise ValueError(f"credible levels must lie in [0, 1], got {tuple(alphas)}")
    # compared in the levels' dtype: a level k / n rounds as alpha does (0.1 in float32 is above
    # 0.1 in float64, and 100 / 1000 in float32 must count as inside the 0.1 region)
    dtype = levels.dtype if levels.is_floating_point() else torch.float64
    grid = torch.tensor(alphas, dtype=dtype, device=levels.device)
    return (levels.reshape(-1, 1) <= grid).double().mean(0)


def expected_calibration_error(
    levels: Tensor, alphas: tuple[float, ...] = CREDIBLE_LEVELS
) -> Tensor:
    """mean over alphas of |coverage(alpha) - alpha| (0: calibrated; at most max(alpha, 1 - alpha)
    averaged); a 0-dim float64 tensor. Args as `coverage`."""
    grid = torch.tensor(alphas, dtype=torch.float64, device=levels.device)
    return (coverage(levels, alphas) - grid).abs().mean()


LEVEL_KNOTS = 20
"""Knots of `fit_level_map`: calibrated levels 0, 1/20, ..., 1 (credible levels at 0.05 steps)."""


@dataclass(frozen=True)
class LevelMap:
    """A monotone recalibration of HPD credible levels (module docstring, `fit_level_map`).

    Attributes:
        masses: (K + 1,) float64, non-decreasing from 0 to 1: masses[k] is the belief mass whose
            HPD region is the calibrated level-k/K region.
    """

    masses: Tensor

    def __post_init__(self) -> None:
        m = torch.as_tensor(self.masses, dtype=torch.float64)
        ok = (
            m.dim() == 1 and m.numel() >= 2 and bool(torch.isfinite(m).all())
            and float(m[0]) == 0.0 and float(m[-1]) == 1.0 and bool((m.diff() >= 0).all())
        )  # fmt: skip
        if not ok:
            raise ValueError(
                "masses must be a 1-D list of at least 2 non-decreasing numbers from 0 to 1, "
                f"got {self.masses!r}"
            )
        object.__setattr__(self, "masses", m)

    @property
    def knots(self) -> Tensor:
        """(K + 1,) the calibrated levels 0, 1/K, ..., 1 of `masses`."""
        return torch.linspace(0.0, 1.0, len(self.masses), dtype=torch.float64)

    def __call__(self, levels: Tensor) -> Tensor:
        """The calibrated levels of HPD levels (`hpd_level`): any shape, float64 out, on the
        levels' device. Between knots linear; at a run of equal masses (no validation level in
        between) the highest of their levels, so that `level <= alpha` keeps its meaning."""
        return _interpolate(levels, self.masses, self.knots)

    def mass(self, alpha: float | Tensor) -> Tensor:
        """The belief mass of the HPD region that is the calibrated level-alpha credible region
        (alpha in [0, 1]; float64)."""
        return _interpolate(torch.as_tensor(alpha, dtype=torch.float64), self.knots, self.masses)


def _interpolate(x: Tensor, xs: Tensor, ys: Tensor) -> Tensor:
    """Piecewise-linear y(x) through (xs, ys), xs non-decreasing; right-continuous at ties."""
    x = x.to(torch.float64)
    xs, ys = xs.to(x.device), ys.to(x.device)
    i = torch.searchsorted(xs, x.clamp(0.0, 1.0).contiguous(), right=True).clamp(1, len(xs) - 1)
    x0, x1, y0, y1 = xs[i - 1], xs[i], ys[i - 1], ys[i]
    width = x1 - x0
    w = torch.where(width > 0, (x - x0) / width.clamp_min(1e-300), torch.ones_like(x))
    return y0 + w.clamp(0.0, 1.0) * (y1 - y0)


def fit_level_map(levels: Tensor, knots: int = LEVEL_KNOTS) -> LevelMap:
    """The map that makes held-out HPD levels uniform (module docstring; Kuleshov et al. 2018).

    Args:
        levels: (...) `hpd_level`s of validation targets under their (tempered) beliefs; at
            least one, all in [0, 1].
        knots: K, the number of steps of the map (its K + 1 masses are the validation levels'
            quantiles at 0, 1/K, ..., 1, with the ends pinned to 0 and 1).

    Returns:
        A `LevelMap`.
    """
    flat = levels.detach().reshape(-1).to(torch.float64).cpu()
    if flat.numel() == 0:
        raise ValueError("fit_level_map: no levels to fit (an empty validation set)")
    if not bool(((flat >= 0) & (flat <= 1)).all()):
        raise ValueError("fit_level_map: levels must lie in [0, 1]")
    if knots < 1:
        raise ValueError(f"knots must be >= 1, got {knots}")
    masses = torch.quantile(flat, torch.linspace(0.0, 1.0, knots + 1, dtype=torch.float64))
    masses[0], masses[-1] = 0.0, 1.0
    return LevelMap(torch.cummax(masses, 0).values)


def credible_radius_deg(
    A: Tensor, level: float = 0.9, num_samples: int = 4096, generator: torch.Generator | None = None
) -> Tensor:
    """The radius in degrees of the smallest geodesic ball around the belief's mode that holds
    the mass `level` (module docstring): "`level` of the belief lies within r of its rotation".

    Estimated from `num_samples` draws of each belief (`rotlearn.bingham.sample`) as the
    empirical `level`-quantile of their angles to the mode: the belief mass inside the estimated
    radius is `level` give or take sqrt(level (1 - level) / num_samples) (0.005 for 0.9 and
    4096 draws).

    Args:
        A: (..., 4, 4) symmetric matrices (their symmetric part is used), finite.
        level: the mass, in (0, 1].
        num_samples: draws per belief, >= 1.
        generator: random source on A's device (None: torch's default).

    Returns:
        (...,) radii in [0, 180] degrees, in A's dtype (float32 for lower precisions). Not
        differentiable.
    """
    _check_A(A)
    if not 0.0 < level <= 1.0:
        raise ValueError(f"level must lie in (0, 1], got {level}")
    if num_samples < 1:
        raise ValueError(f"num_samples must be >= 1, got {num_samples}")
    dtype = A.dtype if A.dtype in (torch.float32, torch.float64) else torch.float32
    batch = A.shape[:-2]
    with torch.no_grad():
        A = _symmetric(A).to(dtype).reshape(-1, 4, 4)
        centre = mode(A)  # (B, 4)
        radii = A.new_empty(A.shape[0])
        rows = max(1, _CHUNK_SAMPLES // num_samples)
        for start in range(0, A.shape[0], rows):
            part = slice(start, start + rows)
            x = sample(A[part], num_samples, generator)  # (rows, n, 4)
            m = centre[part].unsqueeze(1)
            dot = (x * m).sum(-1, keepdim=True)
            off = torch.linalg.vector_norm(x - dot * m, dim=-1)
            angles = torch.rad2deg(2.0 * torch.atan2(off, dot.squeeze(-1).abs()))
            radii[part] = torch.quantile(angles, level, dim=-1)
    return radii.reshape(batch)
