"""The inference API: `rotlearn.load(ckpt)` -> a `Predictor` giving rotations and their uncertainty.

import rotlearn
predictor = rotlearn.load("outputs/runs/<run>/checkpoints/best.ckpt")  # or the run directory
estimate = predictor(points)        # (B, N, 6) matched pairs (u_i, v_i) for the point network
estimate.R, estimate.q              # (B, 3, 3) and (B, 4) quaternions (x, y, z, w), w >= 0
estimate.dispersion, estimate.dt    # A head only: Bingham dispersion (B, 3) and DT score (B,)
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from rotlearn.checkpoint import load_run
from rotlearn.extras import require
from rotlearn.heads import RotationHead

__all__ = ["CHUNK_ELEMENTS", "Predictor", "RotationEstimate", "load"]

# Input numbers sent through the network at once: the Predictor splits larger batches into
# chunks of about this many (at least one sample), so its memory stays bounded for any batch.
CHUNK_ELEMENTS = 2**20


@dataclass(frozen=True)
class RotationEstimate:
    """What a `Predictor` returns for a batch of B inputs.

    Attributes:
        R: (B, 3, 3) rotation matrices.
        q: (B, 4) unit quaternions (x, y, z, w), w >= 0.
        dispersion: (B, 3) Bingham dispersion coefficients (l1 - l4, l1 - l3, l1 - l2) <= 0
            (A head only; more negative = more concentrated belief), else None.
        dt: (B,) dispersion-thresholding score tr(Lambda) = 3 l1 - l2 - l3 - l4 (paper eq. 26;
            A head only; lower = more confident), else None.
        keep: (B,) bool, True where the OOD score passes the checkpoint's calibrated threshold,
            or None when the checkpoint carries no threshold.
    """

    R: Tensor
    q: Tensor
    dispersion: Tensor | None = None
    dt: Tensor | None = None
    keep: Tensor | None = None


class Predictor:
    """A trained network and head, in evaluation mode, that validate what they are given.

    Args:
        net: the backbone; head: the representation head.
        config: the run's resolved config (as saved in the checkpoint).
        ood: optional {"score": "dt", "threshold": float} calibrated on the training set.
        device: where to run.
        chunk_elements: input numbers per forward pass; larger batches are split into chunks
            of whole samples (at least one), so memory is bounded whatever the batch size.
    """

    def __init__(
        self,
        net: nn.Module,
        head: RotationHead,
        config: dict[str, Any] | None = None,
        ood: dict[str, Any] | None = None,
        device: str | torch.device = "cpu",
        chunk_elements: int = CHUNK_ELEMENTS,
    ) -> None:
        if int(chunk_elements) < 1:
            raise ValueError(f"chunk_elements must be a positive integer, got {chunk_elements}")
        self.chunk_elements = int(chunk_elements)
        self.device = torch.device(device)
        self.net = net.to(self.device).eval()
        self.head = head.to(self.device).eval()
        self.config = config or {}
        self.ood = ood
        self.dtype = next(net.parameters()).dtype
        self.in_channels = getattr(net, "in_channels", None)
        self.image_size = (
            getattr(net, "image_size", None) if getattr(net, "channel_axis", -1) == 1 else None
        )

    def _validate(self, inputs: Any) -> Tensor:
        if isinstance(inputs, np.ndarray):
            if not np.issubdtype(inputs.dtype, np.floating):
                raise TypeError(
                    f"inputs must hold floating-point numbers, got dtype {inputs.dtype}"
                )
            inputs = torch.from_numpy(inputs)
        if not isinstance(inputs, Tensor):
            raise TypeError(
                f"inputs must be a torch.Tensor or numpy array, got {type(inputs).__name__}"
            )
        if not inputs.is_floating_point():
            raise TypeError(f"inputs must be floating point (float32/float64), got {inputs.dtype}")
        if self.image_size is not None:
            self._validate_images(inputs)
        elif inputs.ndim < 2 or (
            self.in_channels is not None and inputs.shape[-1] != self.in_channels
        ):
            width = self.in_channels if self.in_channels is not None else "C"
            raise ValueError(
                f"inputs must have shape (B, N, {width}) or (N, {width}) (N points, each "
                f"{width} numbers), got {tuple(inputs.shape)}"
            )
        if inputs.numel() == 0:
            raise ValueError(
                f"inputs are empty (no samples or no points): shape {tuple(inputs.shape)}"
            )
        finite = torch.isfinite(inputs).flatten(1) if inputs.ndim > 2 else torch.isfinite(inputs)
        if not bool(finite.all()):
            bad = (
                "the input" if inputs.ndim == 2 else f"sample {int((~finite.all(-1)).nonzero()[0])}"
            )
            raise ValueError(f"inputs contain NaN or Inf (first at {bad})")
        return inputs

    def _validate_images(self, inputs: Tensor) -> None:
        size, channels = self.image_size, self.in_channels
        if inputs.ndim not in (3, 4) or tuple(inputs.shape[-3:]) != (channels, size, size):
            raise ValueError(
                f"inputs must be stacked image pairs of shape (B, {channels}, {size}, {size}) or "
                f"({channels}, {size}, {size}), got {tuple(inputs.shape)}"
            )

    @torch.no_grad()
    def __call__(self, inputs: Any) -> RotationEstimate:
        """Estimate rotations for (B, N, C) point inputs (or one (N, C) input, as a batch of one),
        or, for image-pair models, (B, C, S, S) normalised pairs (or one (C, S, S))."""
        x = self._validate(inputs)
        if x.ndim == (3 if self.image_size is not None else 2):
            x = x.unsqueeze(0)
        per_sample = max(1, x[:1].numel())
        size = max(1, self.chunk_elements // per_sample)
        parts = [self._predict(chunk) for chunk in x.split(size)]
        R, q, dispersion, dt = (
            torch.cat(values) if values[0] is not None else None
            for values in zip(*parts, strict=True)
        )
        keep = None
        if self.ood is not None and dt is not None and self.ood.get("score") == "dt":
            keep = dt < float(self.ood["threshold"])
        return RotationEstimate(R=R, q=q, dispersion=dispersion, dt=dt, keep=keep)

    def _predict(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
        """R (b, 3, 3), q (b, 4), dispersion (b, 3) and DT (b,) (None without a belief) of one
        chunk of inputs."""
        raw = self.net(x.to(self.device, self.dtype))
        if not bool(torch.isfinite(raw).all()):
            raise FloatingPointError("the network output is not finite for these inputs")
        prediction = self.head(raw)
        return prediction.R, prediction.q, prediction.dispersion, prediction.dt


def load(
    ckpt_path: str | os.PathLike,
    device: str | torch.device = "cpu",
    chunk_elements: int = CHUNK_ELEMENTS,
) -> Predictor:
    """Load a rotlearn checkpoint (or a run directory's last one) as a `Predictor`.

    Goes through `rotlearn.checkpoint.load_run`: the file is read with
    `torch.load(weights_only=True)` (pickled code is refused: `UnsafeCheckpointError`) and the
    saved config may only name allowlisted components (`UntrustedConfigError`, naming the key),
    checked before the network and head are rebuilt from it.
    """
    require("train", "rotlearn.load (it rebuilds the model from the checkpoint's Hydra config)")
    from omegaconf import OmegaConf

    run = load_run(ckpt_path, task="rotation")
    net, head = run.build("net"), run.build("rep")
    net.load_state_dict(run.weights("net"))
    config = OmegaConf.to_container(run.config)
    return Predictor(net, head, config, ood=run.ood, device=device, chunk_elements=chunk_elements)
