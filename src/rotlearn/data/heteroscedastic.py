"""Per-sample difficulty for drawn data: a noise level and a number of distinct points per sample.

Batches stay dense (B, N, C) tensors. A sample with n_i < N distinct points fills its rows
n_i, ..., N - 1 by repeating its own rows (row j holds row j mod n_i), which a max-pooling net
(`rotlearn.nets.PointNet`) cannot tell from the n_i distinct rows alone: duplicates carry no
information, so the net sees exactly n_i points.

Laws (one source for the synthetic Wahba and the ShapeNet data):
- noise level: log-uniform in [lo, hi], i.e. log s ~ U[log lo, log hi] (density 1 / (s log(hi/lo)));
- number of distinct points: uniform on the integers lo, lo + 1, ..., hi.

A batch of such data carries "sigma" (B,), "num_matches" (B,) (int64) and "difficulty" (B,) =
sigma / sqrt(n): for small isotropic noise of std sigma on n points, the least-squares rotation's
angular error scales as sigma / sqrt(n), so the difficulty grows with the expected error of the
best estimate (test metrics rank samples by it, e.g. the noisiest decile).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from rotlearn.errors import ConfigError

__all__ = [
    "check_range",
    "difficulty",
    "keep_random_rows",
    "log_uniform",
    "repeat_rows",
    "uniform_counts",
]


def check_range(
    key: str,
    value: Sequence[float] | None,
    *,
    minimum: float,
    strict: bool = False,
    integer: bool = False,
    maximum: float | None = None,
) -> tuple[float, float] | None:
    """`value` as a (lo, hi) pair with minimum <= lo <= hi (minimum < lo if `strict`), or None.

    Raises:
        ConfigError naming `key` for anything else (not two numbers, out of order, below the
        minimum or above the maximum, not integers where `integer`).
    """
    if value is None:
        return None
    if isinstance(value, str | bytes):
        raise ConfigError(key, f"must be [lo, hi] (two numbers) or null, got {value!r}")
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        lo = hi = math.nan
    if math.isnan(lo) and math.isnan(hi):
        raise ConfigError(key, f"must be [lo, hi] (two numbers) or null, got {value!r}")
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ConfigError(key, f"must be finite, got {value!r}")
    if integer and not (lo.is_integer() and hi.is_integer()):
        raise ConfigError(key, f"must be two integers, got {value!r}")
    if lo > hi:
        raise ConfigError(key, f"needs lo <= hi, got {value!r}")
    if lo < minimum or (strict and lo == minimum):
        bound = f"> {minimum}" if strict else f">= {minimum}"
        raise ConfigError(key, f"needs lo {bound}, got {value!r}")
    if maximum is not None and hi > maximum:
        raise ConfigError(key, f"needs hi <= {maximum}, got {value!r}")
    return lo, hi


def log_uniform(
    size: int,
    lo: float,
    hi: float,
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """(size,) values with log s ~ U[log lo, log hi], 0 < lo <= hi (lo == hi: the constant lo)."""
    t = torch.rand(size, generator=generator, device=device, dtype=dtype)
    return lo * (hi / lo) ** t


def uniform_counts(
    size: int,
    lo: int,
    hi: int,
    *,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """(size,) int64 counts uniform on the integers lo, ..., hi."""
    return torch.randint(int(lo), int(hi) + 1, (size,), generator=generator, device=device)


def repeat_rows(x: Tensor, counts: Tensor) -> Tensor:
    """Keep the first counts[b] rows of each sample and fill the rest by repeating them.

    Args:
        x: (B, N, C).
        counts: (B,) integers in [1, N].

    Returns:
        (B, N, C) with out[b, j] = x[b, j mod counts[b]].
    """
    N = x.shape[-2]
    rows = torch.arange(N, device=x.device) % counts.to(x.device).unsqueeze(-1)  # (B, N)
    return torch.gather(x, -2, rows.unsqueeze(-1).expand(-1, -1, x.shape[-1]))


def difficulty(sigma: Tensor, counts: Tensor) -> Tensor:
    """sigma / sqrt(n), (B,) in sigma's dtype: grows with the best estimate's expected error."""
    return sigma / counts.to(sigma.dtype).sqrt()


def keep_random_rows(
    x: Tensor, counts: Tensor, *, generator: torch.Generator | None = None
) -> Tensor:
    """Keep counts[b] rows of sample b chosen uniformly at random (without replacement) and fill
    the rest by repeating them (`repeat_rows`).

    Args:
        x: (B, N, C); counts: (B,) integers in [1, N].

    Returns:
        (B, N, C): rows 0..counts[b]-1 are distinct rows of x[b], in random order.
    """
    B, N = x.shape[:2]
    keys = torch.rand(B, N, generator=generator, device=generator.device if generator else x.device)
    order = keys.to(x.device).argsort(dim=-1)  # a uniform random permutation per sample
    shuffled = torch.gather(x, -2, order.unsqueeze(-1).expand(-1, -1, x.shape[-1]))
    return repeat_rows(shuffled, counts)
