"""Custom kernels under mixed precision: run them in float32 whatever autocast would pick.

Under `torch.autocast` (CPU or CUDA; Lightning's `precision=bf16-mixed` / `16-mixed`) a network's
linear layers produce bfloat16 or float16 outputs. The rotation maps of this package (eigensolver,
Gram-Schmidt, SVD orthogonalisation) need float32: bfloat16 keeps 8 significant bits, so a rotation
computed in it is orthogonal only to about 4e-3 (some 0.2 degrees), the eigensolver's rounds are
tuned for float32/float64, and several kernels (LU, SVD, sparse products) have no bfloat16
implementation on the CPU. `torch.amp.custom_fwd(cast_inputs=...)` does this for an old-style
`autograd.Function` on one device type; `float32_under_autocast` does it at the public function
boundary for every device type, so it also covers functions that call no custom Function.
`valued_as` is the other half of working in a lower precision: a term valued in float64 (the NLLs'
fit terms, which cancel in float32) with the gradient of its float32 expression.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, TypeVar

import torch
from torch import Tensor

__all__ = ["REDUCED_DTYPES", "autocast_enabled", "float32_under_autocast", "valued_as"]

REDUCED_DTYPES = (torch.float16, torch.bfloat16)  # the dtypes autocast casts to

F = TypeVar("F", bound=Callable[..., Any])


def autocast_enabled(device_type: str) -> bool:
    """Whether autocast is on for `device_type` ("cpu", "cuda", ...); False for device types
    autocast does not support (e.g. "meta")."""
    if not torch.amp.is_autocast_available(device_type):
        return False
    return torch.is_autocast_enabled(device_type)


# One cheap check for "autocast is on for some device type" (private in torch, hence the
# fallback: where it is missing, the per-device check below always runs).
_ANY_AUTOCAST = getattr(torch._C, "_is_any_autocast_enabled", None)


def _upcast(value: Any) -> Any:
    if isinstance(value, Tensor) and value.dtype in REDUCED_DTYPES:
        return value.float()
    return value


def float32_under_autocast(fn: F) -> F:
    """Decorator: where autocast is on for the device of the first tensor argument, cast the
    float16/bfloat16 tensor arguments (positional and keyword) to float32 and call `fn` with
    autocast off for that device; elsewhere call `fn` unchanged (no cost beyond one check).

    So `fn` computes, and returns, float32 for reduced-precision inputs (float64 inputs stay
    float64), and no op inside it is silently lowered to bfloat16 (CPU autocast lowers e.g. mm,
    addmm and matmul). The casts are ordinary differentiable ops: gradients flow back to the
    caller's dtype. The autograd engine runs backward passes outside autocast (Lightning and
    the PyTorch recipes call `backward()` outside the autocast region); custom backwards that
    use matrix products disable it themselves as well.
    """

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        if _ANY_AUTOCAST is not None and not _ANY_AUTOCAST():
            return fn(*args, **kwargs)
        first = next((a for a in (*args, *kwargs.values()) if isinstance(a, Tensor)), None)
        if first is None or not autocast_enabled(first.device.type):
            return fn(*args, **kwargs)
        args = tuple(_upcast(a) for a in args)
        kwargs = {k: _upcast(v) for k, v in kwargs.items()}
        with torch.autocast(first.device.type, enabled=False):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


def valued_as(x: Tensor, value: Tensor) -> Tensor:
    """`x` with the value of `value` (cast to x's dtype) and the gradient of `x`: for a term
    whose value is taken more precisely (e.g. in float64, without a cancellation) than the
    expression that gives its gradient. `value` carries no gradient."""
    return x + (value.detach().to(x.dtype) - x).detach()
