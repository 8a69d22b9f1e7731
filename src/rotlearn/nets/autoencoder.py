"""The convolutional auto-encoder of the OOD baseline (paper section VI-C.1)."""

from __future__ import annotations

import itertools
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Annotated

import torch
from torch import Tensor, nn

from rotlearn.nets.pair_cnn import PAPER_CHANNELS, conv_encoder, encoded_size
from rotlearn.nets.pointnet import mlp
from rotlearn.trust import config_target

if TYPE_CHECKING:  # constraints of the config values, checked by rotlearn.config (pydantic);
    from annotated_types import (  # never evaluated here: torch is all a bare install has
        Gt,
        MinLen,
        MultipleOf,
    )

__all__ = ["ConvAutoEncoder", "conv_decoder", "encoder_sizes"]


def encoder_sizes(image_size: int, layers: int) -> list[int]:
    """Sides of the feature maps of `conv_encoder`, input first: [S, ceil(S / 2), ...]
    (`layers + 1` numbers; the last is `encoded_size(image_size, layers)`)."""
    return [encoded_size(image_size, depth) for depth in range(layers + 1)]


def conv_decoder(channels: Sequence[int], sizes: Sequence[int]) -> nn.Sequential:
    """Transposed convolutions (k3, s2, p1) through the widths `channels` and sides `sizes`.

    Layer i maps (B, channels[i], sizes[i], sizes[i]) to (B, channels[i + 1], sizes[i + 1],
    sizes[i + 1]); its output padding, `sizes[i + 1] - 2 sizes[i] + 1` (1 for an even target side,
    0 for an odd one), restores exactly the side that the matching stride-2 convolution halved
    (rounding up). BatchNorm2d + PReLU follow every layer but the last, which has no activation.
    """
    layers: list[nn.Module] = []
    steps = list(zip(itertools.pairwise(channels), itertools.pairwise(sizes), strict=True))
    for i, ((n_in, n_out), (side_in, side_out)) in enumerate(steps):
        padding = side_out - 2 * side_in + 1
        if padding not in (0, 1):
            raise ValueError(f"cannot upsample side {side_in} to {side_out} with stride 2")
        layers.append(
            nn.ConvTranspose2d(n_in, n_out, 3, stride=2, padding=1, output_padding=padding)
        )
        if i < len(steps) - 1:
            layers += [nn.BatchNorm2d(n_out), nn.PReLU()]
    return nn.Sequential(*layers)


@config_target
class ConvAutoEncoder(nn.Module):
    """Auto-encoder of ONE image of a pair, its reconstruction error an OOD score (paper VI-C.1).

    Encoder: the pair CNN's convolutions (`conv_encoder`, paper VI-C) on C = pair_channels / 2
    channels -> flatten (paper: 1024 x 2 x 2 = 4096) -> Linear hidden -> PReLU -> Linear latent.
    Decoder: Linear latent -> hidden -> PReLU -> Linear flat -> unflatten -> the transposed
    convolutions of `conv_decoder` back to (C, S, S), without an output activation.

    Args:
        pair_channels: channels 2C of a stacked pair (`${data.pair_channels}`: 6 KITTI, 2 MAV).
        image_size: S of the S x S images (`${data.image_size}`).
        channels: widths of the encoder's convolutions (the decoder runs through them backwards).
        hidden: width of the hidden linear layers (paper: 128).
        latent: size of the code (paper: 16).

    `forward`: images (B, C, S, S) -> reconstructions (B, C, S, S).
    """

    def __init__(
        self,
        pair_channels: Annotated[int, Gt(0), MultipleOf(2)] = 6,
        image_size: Annotated[int, Gt(0)] = 224,
        channels: Annotated[Sequence[Annotated[int, Gt(0)]], MinLen(1)] = PAPER_CHANNELS,
        hidden: Annotated[int, Gt(0)] = 128,
        latent: Annotated[int, Gt(0)] = 16,
    ) -> None:
        super().__init__()
        channels = list(channels)
        self.pair_channels, self.image_size = int(pair_channels), int(image_size)
        self.in_channels = self.pair_channels // 2
        sizes = encoder_sizes(self.image_size, len(channels))
        code_shape = (channels[-1], sizes[-1], sizes[-1])
        flat = channels[-1] * sizes[-1] ** 2
        self.encoder = nn.Sequential(
            conv_encoder(self.in_channels, channels), nn.Flatten(1), mlp([flat, hidden, latent])
        )
        self.decoder = nn.Sequential(
            mlp([latent, hidden, flat]),
            nn.Unflatten(1, code_shape),
            conv_decoder([*reversed(channels), self.in_channels], sizes[::-1]),
        )

    def encode(self, images: Tensor) -> Tensor:
        """(B, C, S, S) images -> (B, latent) codes."""
        return self.encoder(images)

    def decode(self, codes: Tensor) -> Tensor:
        """(B, latent) codes -> (B, C, S, S) reconstructions."""
        return self.decoder(codes)

    def forward(self, images: Tensor) -> Tensor:
        """(B, C, S, S) images -> (B, C, S, S) reconstructions."""
        return self.decode(self.encode(images))

    def reconstruction_error(self, pairs: Tensor) -> Tensor:
        """(B, 2C, S, S) stacked pairs -> (B,) mean absolute reconstruction error of the first
        image of each pair (differentiable; the second image is never looked at): the
        auto-encoder's OOD score, >= 0, lower = more in-distribution (eval mode: BatchNorm)."""
        images = self.first_image(pairs)
        return (self(images) - images).abs().flatten(1).mean(1)

    def first_image(self, pairs: Tensor) -> Tensor:
        """The first image (B, C, S, S) of each stacked pair (B, 2C, S, S)."""
        if pairs.ndim != 4 or pairs.shape[1] != self.pair_channels:
            raise ValueError(
                f"pairs must have shape (B, {self.pair_channels}, S, S), got {tuple(pairs.shape)}"
            )
        return pairs[:, : self.in_channels]


def load_autoencoder_net(
    ckpt_path: str | os.PathLike, device: str | torch.device = "cpu"
) -> ConvAutoEncoder:
    """The `ConvAutoEncoder` of a `model=autoencoder` run's checkpoint (or a run directory's last
    one), in eval mode on `device`, read through `rotlearn.checkpoint.load_run` (weights only; the
    saved config may name allowlisted components only). The OOD evaluation's `autoencoder`
    score is its `reconstruction_error`.

    Raises:
        FileNotFoundError: no such checkpoint.
        UnsafeCheckpointError, UntrustedConfigError: see `load_run`.
        ValueError: the checkpoint's net is not an auto-encoder (the message names the path).
    """
    from rotlearn.checkpoint import check_weights, load_run

    run = load_run(ckpt_path)
    target = str(run.config.get("net", {}).get("_target_", ""))
    if not target.endswith("ConvAutoEncoder"):
        raise ValueError(
            f"{run.path} is not an auto-encoder checkpoint: its net is {target or 'missing'!r} "
            "(train one with model=autoencoder, e.g. experiment=kitti_autoencoder)"
        )
    net = run.build("net")  # the net's weights checked, then loaded
    stored = {f"net.{k}": v for k, v in net.state_dict().items()}
    check_weights(stored, run.state_dict, str(run.path))  # and nothing else stored
    return net.to(device).eval()
