"""The point-cloud network of the paper's synthetic and ShapeNet experiments (paper VI-A, VI-B)."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import TYPE_CHECKING, Annotated

import torch
from torch import Tensor, nn

from rotlearn.errors import NonFiniteError
from rotlearn.nets.pooling import LinearMaxPool
from rotlearn.trust import config_target

if TYPE_CHECKING:  # constraints of the config values, checked by rotlearn.config (pydantic);
    from annotated_types import Gt, MinLen  # never evaluated here: torch is all a bare install has

__all__ = ["LOG_GAIN_MAX", "PointNet", "gained", "mlp"]

LOG_GAIN_MAX = 20.0  # the log-gain of `gained` is clamped to [-LOG_GAIN_MAX, LOG_GAIN_MAX]


def gained(out: Tensor) -> Tensor:
    """A net's `output_gain`: (..., k + 1) -> (..., k), the first k numbers times exp(g), g the
    last one clamped to [-LOG_GAIN_MAX, LOG_GAIN_MAX]. Every head's rotation is invariant to a
    positive scale of its input, so g moves only the belief's concentration (A -> e^g A, F -> e^g
    F), on a log scale, which a heteroscedastic belief needs (its concentration spans orders of
    magnitude across samples; a linear output compresses that range, docs/results.md, issue 17)."""
    return out[..., :-1] * out[..., -1:].clamp(-LOG_GAIN_MAX, LOG_GAIN_MAX).exp()


def mlp(sizes: Sequence[int]) -> nn.Sequential:
    """Linear layers with PReLU between them (none after the last)."""
    layers: list[nn.Module] = []
    for i, (n_in, n_out) in enumerate(itertools.pairwise(sizes)):
        if i > 0:
            layers.append(nn.PReLU())
        layers.append(nn.Linear(n_in, n_out))
    return nn.Sequential(*layers)


@config_target
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
        center_init: whether `initialize_from` centres the biases on a batch (the training
            module calls it with the first training batch); False keeps PyTorch's initialisation,
            as in the authors' code.
        output_gain: the last layer also outputs a log-gain g and the output is the other
            out_dim numbers times exp(g) (`gained`): the belief's concentration on a log scale.

    Input (..., N, in_channels) points; output (..., out_dim).
    """

    def __init__(
        self,
        out_dim: Annotated[int, Gt(0)],
        in_channels: Annotated[int, Gt(0)] = 6,
        point_channels: Annotated[Sequence[Annotated[int, Gt(0)]], MinLen(1)] = (64, 128, 1024),
        head_channels: Annotated[Sequence[Annotated[int, Gt(0)]], MinLen(1)] = (256, 128),
        center_init: bool = True,
        output_gain: bool = False,
    ) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.center_init = center_init
        self.output_gain = output_gain
        *hidden, pooled = point_channels
        self.point_mlp = nn.Sequential(*mlp([in_channels, *hidden]), nn.PReLU()) if hidden else None
        self.pool = LinearMaxPool(hidden[-1] if hidden else in_channels, pooled)
        self.head_mlp = mlp([pooled, *head_channels, out_dim + int(output_gain)])

    def forward(self, points: Tensor) -> Tensor:
        features = self.point_mlp(points) if self.point_mlp is not None else points
        out = self.head_mlp(self.pool(features))
        return gained(out) if self.output_gain else out

    @torch.no_grad()
    def initialize_from(self, points: Tensor) -> None:
        """Data-dependent initialisation (Kraehenbuehl et al., ICLR 2016): shift the bias of every
        layer but the last so that, on `points`, each of its outputs has zero mean (over the batch,
        and over the points for the per-point layers). Weights are untouched. A no-op when
        `center_init` is False or the batch holds fewer than 2 samples.

        Why: under PyTorch's default initialisation every max-pooled feature carries a large
        offset shared by all inputs, so the output hardly depends on the input (its spread over a
        batch is about 4 % of its mean). The net first learns the best constant rotation and
        stays near that "predict identity" plateau for 12-15 of the paper's 50 synthetic epochs
        with the 6D head. Centred features shorten the plateau; in the paper's synthetic setting
        6D's final test mean error falls from 1.62 to 1.49 deg (mean over seeds 1-9), see
        docs/results.md.

        Args:
            points: (..., N, in_channels) inputs, e.g. the first training batch.

        Raises:
            NonFiniteError: if `points` holds NaN or inf, or the centred biases would (a batch that
                overflows the layers); the biases are then left as they were. Centring on such
                a batch would make every later output non-finite, whatever the data.
        """
        flat = points.reshape(-1, *points.shape[-2:])
        if not self.center_init or flat.shape[0] < 2:
            return
        if not bool(torch.isfinite(flat).all()):
            n_bad = int((~torch.isfinite(flat)).sum())
            raise NonFiniteError(
                f"PointNet.initialize_from: {n_bad} NaN/inf entries among {flat.numel()} of the "
                f"batch (shape {tuple(points.shape)}): the input batch is itself non-finite "
                "(check the dataset files); biases left unchanged"
            )
        biases = {name: p for name, p in self.named_parameters() if name.endswith("bias")}
        saved = {name: p.clone() for name, p in biases.items()}
        self._centre_biases(flat)
        bad = [  # made non-finite by the centring (one already non-finite is not this batch's)
            name
            for name, p in biases.items()
            if bool(saved[name].isfinite().all()) and not bool(p.isfinite().all())
        ]
        if bad:
            for name, p in biases.items():
                p.copy_(saved[name])
            raise NonFiniteError(
                f"PointNet.initialize_from: centring on this batch makes {bad[0]} non-finite "
                "(the finite inputs overflow the layers): biases left unchanged"
            )

    def _centre_biases(self, flat: Tensor) -> None:
        """Shift each hidden layer's bias by the mean of its output on `flat` (B, N, C)."""

        def centre(layer: nn.Linear, out: Tensor) -> Tensor:
            mean = out.reshape(-1, out.shape[-1]).mean(0)
            layer.bias -= mean
            return out - mean

        def through(layers: Sequence[nn.Module], features: Tensor) -> Tensor:
            for layer in layers:
                features = layer(features)
                if isinstance(layer, nn.Linear):
                    features = centre(layer, features)
            return features

        features = through(self.point_mlp or (), flat)
        features = centre(self.pool.linear, self.pool(features))
        through(self.head_mlp[:-1], features)
