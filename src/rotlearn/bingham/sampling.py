"""Drawing quaternions from the Bingham belief A (Kent, Ganeiber & Mardia 2013).

Quaternions are scalar LAST, (x, y, z, w); the density is p(x) ~ exp(-x^T A x) (`rotlearn.bingham`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from rotlearn.bingham.descriptors import MAX_DISPERSION, _check_A, eigh
from rotlearn.bingham.normalizer import log_normalizer
from rotlearn.geometry.autocast import float32_under_autocast

__all__ = ["sample"]

# ------------------------------------------------------------------------------------- sampling

_MAX_ROUNDS = 64


def _acg_b(shifted: Tensor, iterations: int = 40) -> Tensor:
    """b in [1, 4] with sum_i 1 / (b + 2 l_i) = 1 (Kent et al. 2013), by monotone Newton from 1.

    Any b in (0, 4] gives a valid envelope; this one maximises the acceptance rate.
    """
    b = torch.ones_like(shifted[..., 0])
    for _ in range(iterations):
        t = 1.0 / (b.unsqueeze(-1) + 2.0 * shifted)
        b = b + (t.sum(-1) - 1.0) / (t * t).sum(-1)
    return b.clamp(1.0, 4.0)


def _round_size(remaining: int, rate: float) -> int:
    """Proposals per matrix for the next round: enough for all `remaining` with high chance."""
    expect = remaining / rate
    return math.ceil(expect + 4.0 * math.sqrt(expect) + 16)


@float32_under_autocast
def sample(
    A: Tensor, n: int, generator: torch.Generator | None = None, max_rounds: int = _MAX_ROUNDS
) -> Tensor:
    """Draw n quaternions from each Bingham density p(x) ~ exp(-x^T A x).

    Kent, Ganeiber & Mardia (2013) rejection sampling with an angular central Gaussian envelope
    ACG(Omega), Omega = I + 2 (A - l1 I) / b, vectorised: each round draws proposals for the whole
    batch; accepted ones fill the output in order until every matrix has n.

    Args:
        A: (..., 4, 4) symmetric matrices (finite).
        n: samples per matrix, >= 0.
        generator: random source (its device must be A's).
        max_rounds: cap on the rounds; exceeding it raises RuntimeError (not expected: the
            acceptance rate is at least about 0.45 in 4 dimensions, its high-concentration
            limit, and each round is sized from the exact rate N |Omega|^(1/2) / M).

    Returns:
        (..., n, 4) unit quaternions (x, y, z, w), A's dtype and device; both signs occur
        (the density is antipodally symmetric).
    """
    _check_A(A)
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    if max_rounds < 1:
        raise ValueError(f"max_rounds must be >= 1, got {max_rounds}")
    batch_shape = A.shape[:-2]
    with torch.no_grad():
        ev, V = eigh(A.reshape(-1, 4, 4))
        shifted = (ev - ev[:, :1]).clamp_min(0.0)  # (B, 4), first 0
        b = _acg_b(shifted.double()).to(A.dtype)
        scale = torch.rsqrt(1.0 + 2.0 * shifted / b.unsqueeze(-1))  # std of z in the eigenbasis
        log_m = -(4.0 - b) / 2.0 + 2.0 * torch.log(4.0 / b)  # envelope bound, log
        # exact acceptance rate N(-shifted) |Omega|^(1/2) / M, for sizing the rounds only
        log_rate = (
            log_normalizer(-shifted.clamp_max(MAX_DISPERSION)) - torch.log(scale).sum(-1) - log_m
        )
        rate = float(torch.exp(log_rate).clamp(0.05, 1.0).min()) if ev.shape[0] else 1.0
        rows = ev.shape[0]
        out = A.new_empty(rows, n, 4)
        filled = torch.zeros(rows, dtype=torch.long, device=A.device)
        row_index = torch.arange(rows, device=A.device)
        for _ in range(max_rounds):
            remaining = int((n - filled).max()) if rows else 0
            if remaining <= 0:
                break
            m = _round_size(remaining, rate)
            g = torch.randn(rows, m, 4, generator=generator, device=A.device, dtype=A.dtype)
            y = g * scale.unsqueeze(1)
            y = y / torch.linalg.vector_norm(y, dim=-1, keepdim=True)
            u = (y * y * shifted.unsqueeze(1)).sum(-1)  # y^T (A - l1 I) y in the eigenbasis
            log_ratio = -u + 2.0 * torch.log1p(2.0 * u / b.unsqueeze(-1)) - log_m.unsqueeze(-1)
            unif = torch.rand(rows, m, generator=generator, device=A.device, dtype=A.dtype)
            accept = torch.log(unif) < log_ratio
            position = filled.unsqueeze(-1) + torch.cumsum(accept, dim=-1) - 1
            keep = accept & (position < n)
            r_idx = row_index.unsqueeze(-1).expand(rows, m)[keep]
            out[r_idx, position[keep]] = y[keep]
            filled = (filled + accept.sum(-1)).clamp_max(n)
        else:
            if rows and int(filled.min()) < n:
                raise RuntimeError(
                    f"Bingham rejection sampling did not produce {n} samples in {max_rounds} rounds"
                )
        x = out @ V.mT  # back from the eigenbasis: x = V y
    return x.reshape(*batch_shape, n, 4)
