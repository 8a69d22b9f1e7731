"""The one check of a tensor's trailing shape that every public map of `rotlearn.geometry` makes:
a wrong shape is named at once (`expected a tensor of shape (..., 4), got (3,)`), not as an
unpacking or broadcasting error from deep inside. Shapes are known on the host, so the check
costs no device sync and traces under torch.compile and torch.func."""

from __future__ import annotations

from torch import Tensor

__all__ = ["require_shape"]


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
