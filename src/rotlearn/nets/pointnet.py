"""The point-cloud network of the paper's synthetic and ShapeNet experiments (spec section 3)."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

from torch import Tensor, nn

from rotlearn.nets.pooling import LinearMaxPool

__all__ = ["PointNet", "mlp"]


def mlp(sizes: Sequence[int]) -> nn.Sequential:
    """Linear layers with PReLU between them (none after the last)."""
    layers: list[nn.Module] = []
    for i, (n_in, n_out) in enumerate(itertools.pairwise(sizes)):
        if i > 0:
            layers.append(nn.PReLU())
        layers.append(nn.Linear(n_in, n_out))
    return nn.Sequential(*layers)


class PointNet(nn.Module):
    """Shared per-point MLP, global max-pool, then an MLP to the head's `out_dim` numbers.

    Per point: in_channels -> 64 -> 128 -> 1024 (PReLU between, none before the pool), max over
    points, then 1024 -> 256 -> 128 -> out_dim with PReLU: the original Conv1d(kernel_size=1)
    stack. The last per-point layer and the pool are one `LinearMaxPool`, whose backward only
    visits the points the max selected (same values and gradients, about half the step time).

    Args:
        out_dim: size of the representation (`${rep.out_dim}`).
        in_channels: features per point (6 for a matched pair (u_i, v_i)).
        point_channels: widths of the per-point layers (the last one is pooled).
        head_channels: widths of the hidden layers after pooling.

    Input (..., N, in_channels) points; output (..., out_dim).
    """

    def __init__(
        self,
        out_dim: int,
        in_channels: int = 6,
        point_channels: Sequence[int] = (64, 128, 1024),
        head_channels: Sequence[int] = (256, 128),
    ) -> None:
        super().__init__()
        self.in_channels = in_channels
        *hidden, pooled = point_channels
        self.point_mlp = nn.Sequential(*mlp([in_channels, *hidden]), nn.PReLU()) if hidden else None
        self.pool = LinearMaxPool(hidden[-1] if hidden else in_channels, pooled)
        self.head_mlp = mlp([pooled, *head_channels, out_dim])

    def forward(self, points: Tensor) -> Tensor:
        features = self.point_mlp(points) if self.point_mlp is not None else points
        return self.head_mlp(self.pool(features))
