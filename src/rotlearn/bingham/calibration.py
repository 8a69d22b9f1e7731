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
"""

from __future__ import annotations

import torch
from torch import Tensor

from rotlearn.bingham.descriptors import _check_A, _float_dtype, _raise_first, _symmetric, mode
from rotlearn.bingham.sampling import sample

__all__ = [
    "CREDIBLE_LEVELS",
    "coverage",
    "credible_radius_deg",
    "expected_calibration_error",
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
    x^T A x < q^T A q; standard deviation <= 1 / (2 sqrt(num_samples)). Computed with A shifted to
    A - l1 I (same regions) so that concentrated beliefs keep their precision in float32.

    Args:
        A: (..., 4, 4) symmetric matrices (their symmetric part is used), finite.
        q: (..., 4) unit quaternions (x, y, z, w), batch shape broadcast against A's (each
            broadcast pair gets its own draws).
        num_samples: draws per belief, >= 1.
        generator: random source on A's device (None: torch's default).

    Returns:
        (...,) levels in [0, 1] (multiples of 1 / num_samples), in the promoted dtype of A and q
        (float32 for lower precisions); q inside the level-alpha region iff level <= alpha.
        Not differentiable.
    """
    _check_A(A)
    _float_dtype(q, "q")
    if q.shape[-1] != 4:
        raise ValueError(f"q must have shape (..., 4), got {tuple(q.shape)}")
    _raise_first(~torch.isfinite(q).all(-1), "q has NaN or Inf")
    if num_samples < 1:
        raise ValueError(f"num_samples must be >= 1, got {num_samples}")
    dtype = torch.promote_types(A.dtype, q.dtype)
    dtype = dtype if dtype in (torch.float32, torch.float64) else torch.float32
    batch = torch.broadcast_shapes(A.shape[:-2], q.shape[:-1])
    with torch.no_grad():
        A = _symmetric(A).to(dtype).expand(*batch, 4, 4).reshape(-1, 4, 4)
        q = q.to(dtype).expand(*batch, 4).reshape(-1, 4)
        l1 = torch.linalg.eigvalsh(A)[:, :1]
        S = A - l1.unsqueeze(-1) * torch.eye(4, dtype=dtype, device=A.device)
        target = torch.einsum("bi,bij,bj->b", q, S, q)
        levels = torch.empty_like(target)
        rows = max(1, _CHUNK_SAMPLES // num_samples)
        for start in range(0, A.shape[0], rows):
            part = slice(start, start + rows)
            x = sample(A[part], num_samples, generator)  # (rows, n, 4)
            s = torch.einsum("bni,bij,bnj->bn", x, S[part], x)
            below = (s < target[part].unsqueeze(-1)).sum(-1)
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
