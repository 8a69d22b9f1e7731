"""A siamese pair network with a correlation (cost-volume) layer, for small relative rotations.

Beyond the paper (issue 15): a rotation of about a degree moves a 64-pixel image by about a pixel,
which the stacked-pair CNN (`PairCNN`) must discover from scratch. Here each frame goes through one
shared encoder, and the correlation of frame 1's features with frame 2's features shifted by every
displacement in a small window (the cost volume of optical-flow networks, e.g. FlowNetC, PWC-Net)
makes the image motion explicit: at each feature pixel, which shift matches best. A small CNN and
MLP regress the head's numbers from the cost volume; its spatial layout is kept to the end, so
yaw / pitch (a shift) and roll (a rotation about the image centre) are told apart.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import TYPE_CHECKING, Annotated

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from rotlearn.nets.pair_cnn import conv_encoder, encoded_size
from rotlearn.nets.pointnet import gained, mlp
from rotlearn.trust import config_target

if TYPE_CHECKING:  # constraints of the config values, checked by rotlearn.config (pydantic);
    from annotated_types import (  # never evaluated here: torch is all a bare install has
        Ge,
        Gt,
        MinLen,
        MultipleOf,
    )

__all__ = ["PairCorrelationNet", "correlation"]


def correlation(first: Tensor, second: Tensor, radius: int) -> Tensor:
    """The cost volume of two feature maps over a (2 radius + 1)^2 displacement window.

    out[..., k, y, x] = mean_c first[..., c, y, x] * second[..., c, y + dy, x + dx] for the
    displacement (dy, dx) = (k // (2r + 1) - r, k % (2r + 1) - r); `second` is zero outside.

    Args:
        first, second: (..., C, H, W) feature maps of the same shape (any batch shape).
        radius: r >= 0, the largest displacement in feature pixels along each axis.

    Returns:
        (..., (2r + 1)^2, H, W): one shifted product per displacement, each over the whole
        batch (a view of the padded `second`, not a copy).
    """
    if first.shape != second.shape or first.ndim < 3:
        raise ValueError(
            f"need two (..., C, H, W) maps of one shape, got {tuple(first.shape)} and "
            f"{tuple(second.shape)}"
        )
    if radius < 0:
        raise ValueError(f"radius must be >= 0, got {radius}")
    height, width = first.shape[-2:]
    padded = F.pad(second, (radius, radius, radius, radius))
    side = range(2 * radius + 1)
    costs = [
        (first * padded[..., dy : dy + height, dx : dx + width]).mean(-3)
        for dy, dx in itertools.product(side, side)
    ]
    return torch.stack(costs, dim=-3)


@config_target
class PairCorrelationNet(nn.Module):
    """Stacked image pair -> `out_dim` numbers through a siamese encoder and a cost volume.

    frame 1, frame 2 (the two halves of the stacked channels) -> the same frame encoder
    (`conv_encoder(..., refine=True)`: per width in `channels` a stride-2 and a stride-1
    convolution, stride 2^len(channels) in all) -> `correlation` over displacements of up to
    `radius` feature pixels -> LeakyReLU(0.1) -> `conv_encoder` (`head_channels`, stride-2
    convolutions) -> flatten -> Linear `hidden` -> PReLU -> Linear `out_dim`.

    Args:
        out_dim: size of the representation (`${rep.out_dim}`).
        in_channels: channels of the stacked pair (`${data.pair_channels}`: 6 KITTI, 2 MAV);
            even, each frame has half.
        image_size: S of the S x S input (`${data.image_size}`).
        channels: widths of the frame encoder's stages (each halves the resolution).
        radius: largest displacement of the cost volume, in feature pixels (S = 64 with two
            stages: 16 x 16 features, radius 2 covers shifts of up to 8 input pixels, about
            12 degrees of yaw on the 80-degree KITTI-format demo frames).
        head_channels: widths of the stride-2 convolutions on the cost volume.
        hidden: width of the hidden linear layer.
        output_gain: one more output, a log-gain g of the other out_dim numbers
            (`rotlearn.nets.pointnet.gained`): the belief's concentration on a log scale.

    The defaults are the demo recipe (`experiment=kitti_ood_demo`, `mav_ood_demo`; measured in
    docs/results.md, issue 15): about 1.6x the step time of the demo-sized `PairCNN` on a CPU.

    Input (B, in_channels, S, S); output (B, out_dim).
    """

    channel_axis = 1  # inputs are (B, C, S, S) images (the inference API checks this)

    def __init__(
        self,
        out_dim: Annotated[int, Gt(0)],
        in_channels: Annotated[int, Gt(0), MultipleOf(2)] = 6,  # two stacked frames
        image_size: Annotated[int, Gt(0)] = 224,
        channels: Annotated[Sequence[Annotated[int, Gt(0)]], MinLen(1)] = (16, 32),
        radius: Annotated[int, Ge(0)] = 2,
        head_channels: Annotated[Sequence[Annotated[int, Gt(0)]], MinLen(1)] = (64, 128, 128),
        hidden: Annotated[int, Gt(0)] = 256,
        output_gain: bool = False,
    ) -> None:
        super().__init__()
        self.in_channels, self.image_size, self.radius = in_channels, image_size, radius
        self.output_gain = output_gain
        self.encoder = conv_encoder(in_channels // 2, channels, refine=True)
        self.mixer = conv_encoder((2 * radius + 1) ** 2, head_channels)
        side = encoded_size(encoded_size(image_size, len(channels)), len(head_channels))
        self.regressor = mlp([head_channels[-1] * side**2, hidden, out_dim + int(output_gain)])

    def forward(self, pairs: Tensor) -> Tensor:
        batch, frame = pairs.shape[0], self.in_channels // 2
        frames = pairs.reshape(batch * 2, frame, *pairs.shape[-2:])  # both frames, one pass
        features = self.encoder(frames).unflatten(0, (batch, 2))
        cost = correlation(features[:, 0], features[:, 1], self.radius)
        out = self.regressor(self.mixer(F.leaky_relu(cost, 0.1)).flatten(1))
        return gained(out) if self.output_gain else out
