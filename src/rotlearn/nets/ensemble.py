"""The backbone of an ensemble: every member's network on the same input (`rotlearn.heads.
ensemble.EnsembleHead` combines their outputs)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

__all__ = ["EnsembleNet"]


class EnsembleNet(nn.Module):
    """K networks side by side: (B, ...) input -> (B, K, d) outputs, member k's in row k,
    zero-padded to d, the widest member's output.

    The input must suit every member (the same input layout); `in_channels`, `image_size` and
    `channel_axis` (read by `rotlearn.inference.Predictor` to check inputs) are the first
    member's.

    Args:
        nets: the members' networks.
    """

    def __init__(self, nets: Sequence[nn.Module]) -> None:
        super().__init__()
        nets = list(nets)
        if not nets:
            raise ValueError("an ensemble needs at least one member")
        self.nets = nn.ModuleList(nets)
        for name in ("in_channels", "image_size", "channel_axis"):
            if hasattr(nets[0], name):
                setattr(self, name, getattr(nets[0], name))

    def forward(self, x: Tensor) -> Tensor:
        outputs = [net(x) for net in self.nets]
        width = max(o.shape[-1] for o in outputs)
        padded = [nn.functional.pad(o, (0, width - o.shape[-1])) for o in outputs]
        return torch.stack(padded, dim=-2)
