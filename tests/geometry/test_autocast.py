"""float32_under_autocast: reduced-precision arguments become float32 and the function runs with
autocast off, only where autocast is on for the arguments' device."""

from __future__ import annotations

import pytest
import torch

from rotlearn.geometry import autocast as amp
from rotlearn.geometry.autocast import autocast_enabled, float32_under_autocast


@float32_under_autocast
def product(a: torch.Tensor, b: torch.Tensor, *, c: torch.Tensor | None = None) -> tuple:
    """What the body sees: the dtypes of its arguments, autocast's state, and a matmul's dtype."""
    dtypes = (a.dtype, b.dtype, None if c is None else c.dtype)
    return dtypes, torch.is_autocast_enabled("cpu"), (a @ b).dtype


@pytest.mark.parametrize("fast_check", [True, False])
def test_casts_reduced_arguments_and_turns_autocast_off(monkeypatch, fast_check):
    if not fast_check:  # a torch without the private one-call check takes the per-device path
        monkeypatch.setattr(amp, "_ANY_AUTOCAST", None)
    a = torch.ones(2, 2, dtype=torch.bfloat16)
    b = torch.ones(2, 2, dtype=torch.float64)
    c = torch.ones(2, dtype=torch.float16)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert (torch.ones(2, 2) @ torch.ones(2, 2)).dtype == torch.bfloat16  # autocast is on
        dtypes, inside, matmul = product(a, b.float(), c=c)
        assert torch.is_autocast_enabled("cpu")  # and restored afterwards
    assert dtypes == (torch.float32, torch.float32, torch.float32)  # float64 would stay float64
    assert not inside and matmul == torch.float32
    # outside autocast nothing changes: the function sees its arguments as given
    dtypes, inside, _ = product(b, b, c=c)
    assert dtypes == (torch.float64, torch.float64, torch.float16) and not inside


def test_float64_is_left_alone_and_other_devices_unaffected():
    b = torch.ones(2, 2, dtype=torch.float64)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert product(b, b)[0][:2] == (torch.float64, torch.float64)
    assert not autocast_enabled("meta")  # a device type without autocast
    meta = torch.empty(2, 2, device="meta", dtype=torch.bfloat16)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert product(meta, meta)[0][:2] == (torch.bfloat16, torch.bfloat16)


def test_valued_as_takes_the_value_of_one_and_the_gradient_of_the_other():
    x = torch.tensor([1.0, 2.0], requires_grad=True)
    precise = torch.tensor([1.25, -3.5], dtype=torch.float64, requires_grad=True)
    out = amp.valued_as(3 * x, precise)
    assert out.dtype == torch.float32 and out.tolist() == [1.25, -3.5]
    out.sum().backward()
    assert x.grad.tolist() == [3.0, 3.0] and precise.grad is None
