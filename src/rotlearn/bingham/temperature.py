"""Post-hoc temperature scaling of Bingham beliefs: the T that makes A / T fit held-out targets.

Quaternions are scalar LAST, (x, y, z, w); the density is p(q) ~ exp(-q^T A q) w.r.t. the uniform
probability measure on S^3 (`rotlearn.bingham`). Tempering divides A by a scalar T > 0: the mode
is unchanged, T > 1 widens the belief and T < 1 sharpens it.

With beta = 1 / T, e = q^T A q - l1 >= 0 (the target's "energy" above the mode) and the dispersion
lam of A (paper III-C), the per-sample NLL of the tempered belief is (paper eq. 19)

    nll(A / T, q) = beta e + log N(beta lam),

an exponential family in beta (natural parameter -beta, sufficient statistic e) plus nothing else,
so the mean NLL is CONVEX in beta. Its derivative

    d/dbeta mean nll = mean_i [ e_i + lam_i . m(beta lam_i) ] = mean_i [ e_i - E_beta,i[e] ],

with m the second moments (`rotlearn.bingham.moments`, exact gradient of log N), increases with
beta: the minimiser is where the observed mean energy equals the belief's expected one. It is
found by bisection on the sign of that derivative over log beta, in float64, inside the bracket
where every tempered belief stays supported, beta (l4 - l1) <= MAX_DISPERSION, and above a
near-uniform end, beta (l4 - l1) >= 1e-6 for the widest sample. Both ends scale with A, so the
fit is equivariant: T(c A) = c T(A).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from rotlearn.bingham.descriptors import (
    MAX_DISPERSION,
    _check_A,
    _check_q,
    _symmetric,
    dispersion_from_eigenvalues,
    eigenvalues,
)
from rotlearn.bingham.normalizer import _log_normalizer3, moments

__all__ = ["MIN_SPREAD_RATIO", "TemperatureFit", "fit_temperature", "temperature_refusal"]

MIN_SPREAD_RATIO = 1e-6
"""The near-uniform end of the bracket: beta (l4 - l1) >= this for the widest-spread sample."""

_MAX_SPREAD_RATIO = MAX_DISPERSION * (1.0 - 1e-9)  # the supported end, with rounding margin


@dataclass(frozen=True)
class TemperatureFit:
    """The result of `fit_temperature`.

    Attributes:
        temperature: 0-dim tensor T > 0 in A's dtype (A -> A / T).
        nll_before: mean NLL (nats, w.r.t. the uniform measure on S^3) of the untempered beliefs,
            or NaN where A's eigenvalue spread exceeds MAX_DISPERSION (not computable).
        nll_after: mean NLL of the tempered beliefs A / T.
        num: how many (A, q) pairs were fitted.
        at_bound: True where the optimum lies at or beyond the bracket (the NLL still falls
            towards the end): "lower" (T as small as supported: the targets sit at the modes)
            or "upper" (T near-uniform: the beliefs carry no information); None inside.
    """

    temperature: Tensor
    nll_before: float
    nll_after: float
    num: int
    at_bound: str | None = None


def _flatten(A: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
    """A (N, 4, 4) and q (N, 4), float64, after validation and broadcasting."""
    _check_A(A)
    _check_q(q)
    try:
        shape = torch.broadcast_shapes(A.shape[:-2], q.shape[:-1])
    except RuntimeError:
        raise ValueError(
            f"batch shapes of A {tuple(A.shape[:-2])} and q {tuple(q.shape[:-1])} do not broadcast"
        ) from None
    if math.prod(shape) == 0:
        raise ValueError("no samples to fit a temperature on (empty batch)")
    A = _symmetric(A).to(torch.float64).expand(*shape, 4, 4).reshape(-1, 4, 4)
    return A, q.to(torch.float64).expand(*shape, 4).reshape(-1, 4)


def _mean_nll(energy: Tensor, lam: Tensor, beta: float) -> float:
    """mean_i [beta e_i + log N(beta lam_i)]."""
    scaled = (beta * lam).clamp(-MAX_DISPERSION, 0.0)
    with torch.no_grad():
        return float((beta * energy + _log_normalizer3(scaled)).mean())


def _slope(energy: Tensor, lam: Tensor, beta: float) -> float:
    """d/dbeta of the mean NLL: mean_i [e_i + lam_i . m(beta lam_i)] (increasing in beta)."""
    m = moments((beta * lam).clamp(-MAX_DISPERSION, 0.0))
    return float((energy + (lam * m).sum(-1)).mean())


def fit_temperature(
    A: Tensor, q: Tensor, *, rtol: float = 1e-10, max_iter: int = 200
) -> TemperatureFit:
    """Fit the temperature T minimising the mean of `nll(A / T, q)` (module docstring).

    Args:
        A: (..., 4, 4) symmetric matrices of the beliefs (their symmetric part is used), finite.
        q: (..., 4) the targets, unit quaternions (x, y, z, w); batch shape broadcast against A's.
            Every pair counts once.
        rtol: relative tolerance on T (the bisection stops when the bracket on log beta is
            narrower than this).
        max_iter: cap on the bisection steps.

    Returns:
        `TemperatureFit`: T (0-dim, A's dtype), the mean NLL before and after, the sample count,
        and whether the optimum lies at the bracket's end.

    Raises:
        ValueError: no samples, NaN/Inf in A or q (naming the first batch index), or every A a
            multiple of the identity (a uniform belief: no temperature changes it).
        TypeError: A or q not floating point.
    """
    if not rtol > 0:
        raise ValueError(f"rtol must be > 0, got {rtol}")
    A64, q64 = _flatten(A, q)
    with torch.no_grad():
        ev = eigenvalues(A64)
        energy = (q64.unsqueeze(-2) @ A64 @ q64.unsqueeze(-1)).reshape(-1) - ev[:, 0]
        energy = energy.clamp_min(0.0)  # >= 0 up to rounding (q need not be exactly unit)
        lam = dispersion_from_eigenvalues(ev).clamp_max(0.0)  # (N, 3), <= 0
    spread = float(-lam[:, 0].min())  # the largest l4 - l1
    if not spread > 0:
        raise ValueError(
            "every A is a multiple of the identity (a uniform belief): no temperature changes it"
        )
    lo, hi = math.log(MIN_SPREAD_RATIO / spread), math.log(_MAX_SPREAD_RATIO / spread)
    at_bound = None
    if _slope(energy, lam, math.exp(hi)) <= 0:  # still falling at the sharpest supported belief
        log_beta, at_bound = hi, "lower"
    elif _slope(energy, lam, math.exp(lo)) >= 0:  # already rising at the near-uniform end
        log_beta, at_bound = lo, "upper"
    else:
        for _ in range(max_iter):
            if hi - lo <= rtol:
                break
            mid = 0.5 * (lo + hi)
            if _slope(energy, lam, math.exp(mid)) > 0:
                hi = mid
            else:
                lo = mid
        log_beta = 0.5 * (lo + hi)
    beta = math.exp(log_beta)
    before = _mean_nll(energy, lam, 1.0) if spread <= MAX_DISPERSION else math.nan
    return TemperatureFit(
        temperature=torch.tensor(1.0 / beta, dtype=A.dtype),
        nll_before=before,
        nll_after=_mean_nll(energy, lam, beta),
        num=int(energy.shape[0]),
        at_bound=at_bound,
    )


def temperature_refusal(head: object, model: object = None) -> str | None:
    """Why a model with `head` has no belief whose temperature can be fitted (None: the head
    defines one, `defines_belief`). Asked for `calibrate: true` by `rotlearn.config` once the
    head is built (before Lightning is imported) and by `rotlearn.lit.PostHocCalibration`;
    `model` (its class, or its config node) is named when it has no head."""
    if getattr(head, "defines_belief", False):
        return None
    if head is None:
        name = model.get("_target_") if isinstance(model, dict) else type(model).__name__
        return f"fits the temperature of a belief; the model {name} has no head"
    return f"fits the temperature of a belief; rep={getattr(head, 'name', None)} has none"
