"""The image-pair CNN of the paper's KITTI and MAV experiments (paper section VI-C)."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import TYPE_CHECKING, Annotated

from torch import Tensor, nn

from rotlearn.nets.pointnet import gained, mlp
from rotlearn.trust import config_target

if TYPE_CHECKING:  # constraints of the config values, checked by rotlearn.config (pydantic);
    from annotated_types import Gt, MinLen  # never evaluated here: torch is all a bare install has

# The paper's convolution widths (section VI-C): 224 -> 2 pixels in seven stride-2 steps.
PAPER_CHANNELS = (64, 128, 256, 512, 1024, 1024, 1024)

__all__ = ["PairCNN", "conv_encoder", "encoded_size"]


def conv_encoder(in_channels: int, channels: Sequence[int], refine: bool = False) -> nn.Sequential:
    """[Conv2d(k3, s2, p1), BatchNorm2d, PReLU] per width in `channels`: each halves H and W
    (rounding up); with `refine`, each stage adds [Conv2d(k3, s1, p1), BatchNorm2d, PReLU] at its
    width. Input (B, in_channels, H, W); output (B, channels[-1], H', W')."""
    layers: list[nn.Module] = []
    for n_in, n_out in itertools.pairwise([in_channels, *channels]):
        strides = (2, 1) if refine else (2,)
        for n, stride in zip((n_in, n_out), strides, strict=False):
            layers += [
                nn.Conv2d(n, n_out, 3, stride=stride, padding=1),
                nn.BatchNorm2d(n_out),
                nn.PReLU(),
            ]
    return nn.Sequential(*layers)


def encoded_size(image_size: int, layers: int) -> int:
    """Side of the feature map after `layers` stride-2 convolutions of `conv_encoder`."""
    for _ in range(layers):
        image_size = (image_size + 1) // 2
    return image_size


@config_target
class PairCNN(nn.Module):
    """Stacked image pair -> `out_dim` numbers (paper section VI-C).

    Paper: 7 convolutions 6 -> 64 -> 128 -> 256 -> 512 -> 1024 -> 1024 -> 1024 (224 -> 2 pixels),
    flatten (4096) -> Linear 512 -> PReLU -> Linear out_dim.

    Args:
        out_dim: size of the representation (`${rep.out_dim}`).
        in_channels: channels of the stacked pair (`${data.pair_channels}`: 6 KITTI, 2 MAV).
        image_size: S of the S x S input (`${data.image_size}`).
        channels: widths of the convolutions.
        hidden: width of the hidden linear layer.
        output_gain: one more output, a log-gain g of the other out_dim numbers
            (`rotlearn.nets.pointnet.gained`): the belief's concentration on a log scale.

    Input (B, in_channels, S, S); output (B, out_dim).
    """

    channel_axis = 1  # inputs are (B, C, S, S) images (the inference API checks this)

    def __init__(
        self,
        out_dim: Annotated[int, Gt(0)],
        in_channels: Annotated[int, Gt(0)] = 6,
        image_size: Annotated[int, Gt(0)] = 224,
        channels: Annotated[Sequence[Annotated[int, Gt(0)]], MinLen(1)] = PAPER_CHANNELS,
        hidden: Annotated[int, Gt(0)] = 512,
        output_gain: bool = False,
    ) -> None:
        super().__init__()
        self.in_channels, self.image_size = in_channels, image_size
        self.output_gain = output_gain
        self.encoder = conv_encoder(in_channels, channels)
        flat = channels[-1] * encoded_size(image_size, len(channels)) ** 2
        self.regressor = mlp([flat, hidden, out_dim + int(output_gain)])

    def forward(self, pairs: Tensor) -> Tensor:
        out = self.regressor(self.encoder(pairs).flatten(1))
        return gained(out) if self.output_gain else out
