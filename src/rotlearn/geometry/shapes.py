"""The one check of a tensor's trailing shape that every public map of `rotlearn.geometry` makes:
a wrong shape is named at once (`expected a tensor of shape (..., 4), got (3,)`), not as an
unpacking or broadcasting error from deep inside. Shapes are known on the host, so the check
costs no device sync and traces under torch.compile and torch.func. And `promoted`: the inputs
of a map of two tensors in one dtype, as torch's elementwise ops promote them (a float32 and a
float64 give float64), where a matmul would refuse the pair."""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["promoted", "require_shape"]


def require_shape(x: Tensor, trailing: tuple[int, ...], name: str = "the input") -> None:
    """Raise ValueError unless `x` is a tensor of shape (..., *trailing).

    Args:
        x: the tensor.
        trailing: its last dimensions, e.g. (4,) for quaternions, (3, 3) for rotation matrices.
        name: the argument, for the message.
    """
    try:  # the common case in one comparison (torch.Size and numpy shapes compare to tuples)
        if x.shape[-len(trailing) :] == trailing:
            return
    except AttributeError:
        pass
    wanted = ", ".join(["...", *map(str, trailing)])
    got = tuple(x.shape) if hasattr(x, "shape") else type(x).__name__
    raise ValueError(f"{name}: expected a tensor of shape ({wanted}), got {got}")


def promoted(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    """`a` and `b` in their promoted dtype (`torch.promote_types`): float32 with float64 is
    float64, as for `a - b`; each unchanged where it has that dtype already."""
    dtype = torch.promote_types(a.dtype, b.dtype)
    return a.to(dtype), b.to(dtype)
