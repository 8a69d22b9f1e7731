"""The inference API: `rotlearn.load(ckpt)` -> a `Predictor` giving rotations and their uncertainty.

Example::

    import rotlearn
    predictor = rotlearn.load("outputs/runs/<run>/checkpoints/best.ckpt")  # or the run directory
    estimate = predictor(points)        # (B, N, 6) matched pairs (u_i, v_i) for the point network
    estimate.R, estimate.q              # (B, 3, 3) and (B, 4) quaternions (x, y, z, w), w >= 0
    estimate.dispersion, estimate.dt    # belief heads (A, Fisher): dispersion (B, 3), DT (B,)
    estimate.A, estimate.temperature    # the belief p(q) ~ exp(-q^T A q), (B, 4, 4), tempered by T
    estimate.sample(100)                # (B, 100, 4) quaternions drawn from each belief
    estimate.log_prob(R_or_q)           # (B,) or (B, n) log densities of rotations / quaternions

The belief (heads that define one: `rep=a`, and the matrix Fisher head, whose `A` is the Bingham
matrix of the same density and whose `F` is carried too) is the Bingham density
p(q; A) = exp(-q^T A q) / Z(A) over unit quaternions (x, y, z, w), antipodally symmetric, so also a
density on SO(3). `log_prob` is w.r.t. the uniform probability measure (the Haar probability on
SO(3), the uniform measure on S^3): a value > 0 means more likely than uniform. When the run was
trained with `calibrate=true`, the checkpoint's temperature T (`checkpoints/temperature.json`) is
applied: A, F, the dispersion and the DT score are those of the calibrated belief A / T (and the
OOD keep flags compare that DT with the threshold calibrated on the same scale).

Credible regions. The highest-density region of level a is {R : log p(R) >= c_a}, with c_a the
(1 - a)-quantile of log p over the belief's own samples; it holds the fraction a of the belief's
mass. Per estimate, by Monte Carlo (error ~ sqrt(a (1 - a) / n) in the level)::

    draws = estimate.sample(4096)                                # (B, 4096, 4)
    c = estimate.log_prob(draws).quantile(1 - 0.9, dim=-1)       # (B,) the 90 % cut
    inside = estimate.log_prob(R_candidate) >= c                 # (B,) bool: R in the region

The radius of the smallest ball around the mode holding the mass a, in degrees ("a of the belief
lies within r of the rotation"), is `rotlearn.bingham.credible_radius_deg(estimate.A, a)`.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from rotlearn import bingham
from rotlearn.checkpoint import load_run
from rotlearn.extras import require
from rotlearn.geometry import rotmat_to_quat
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
        A: (B, 4, 4) the Bingham belief p(q) ~ exp(-q^T A q) (paper eqs. 8, 14), tempered
            (A / T), for heads that define a belief, else None.
        F: (B, 3, 3) the matrix Fisher parameter, p(R) ~ exp(tr(F^T R)), tempered (F / T), for
            the Fisher head, else None.
        temperature: the post-hoc temperature T applied (1.0: none).

    dispersion and dt are those of the tempered belief A.
    """

    R: Tensor
    q: Tensor
    dispersion: Tensor | None = None
    dt: Tensor | None = None
    keep: Tensor | None = None
    A: Tensor | None = None
    F: Tensor | None = None
    temperature: float = 1.0

    def _belief(self) -> Tensor:
        if self.A is None:
            raise ValueError(
                "this model's head defines no belief (only rep=a and the Fisher head do): "
                "nothing to sample or score"
            )
        return self.A

    def sample(self, n: int, generator: torch.Generator | None = None) -> Tensor:
        """Draw n quaternions (x, y, z, w) from each belief: (B, n, 4), both signs occurring
        (`rotlearn.bingham.sample`; `generator` on the estimate's device).

        Raises:
            ValueError: the head defines no belief.
        """
        return bingham.sample(self._belief(), n, generator=generator)

    def log_prob(self, x: Tensor) -> Tensor:
        """Log densities of rotations under each belief, w.r.t. the uniform probability measure
        on SO(3) (equivalently on S^3; `rotlearn.bingham.log_prob`).

        Args:
            x: quaternions (x, y, z, w) of shape (B, 4) or (B, n, 4), or rotation matrices
                (B, 3, 3) or (B, n, 3, 3): one or n per estimate.

        Returns:
            (B,) or (B, n), in the belief's dtype.

        Raises:
            ValueError: the head defines no belief, or x has another shape.
        """
        A = self._belief()
        if not isinstance(x, Tensor):
            raise TypeError(f"x must be a torch.Tensor, got {type(x).__name__}")
        if x.shape[-2:] == (3, 3) and x.dim() in (3, 4):
            q = rotmat_to_quat(x.to(A.device, A.dtype))
        elif x.shape[-1] == 4 and x.dim() in (2, 3):
            q = x.to(A.device, A.dtype)
        else:
            raise ValueError(
                "x must be quaternions (B, 4) or (B, n, 4), or rotation matrices (B, 3, 3) or "
                f"(B, n, 3, 3), got {tuple(x.shape)}"
            )
        if q.shape[0] != A.shape[0]:
            raise ValueError(f"x holds {q.shape[0]} entries for {A.shape[0]} estimates")
        if q.dim() == 3:
            A = A.unsqueeze(1)
        return bingham.log_prob(A, q)


class Predictor:
    """A trained network and head, in evaluation mode, that validate what they are given.

    Args:
        net: the backbone; head: the representation head.
        config: the run's resolved config (as saved in the checkpoint).
        ood: optional {"score": "dt", "threshold": float} calibrated on the training set.
        temperature: the belief's post-hoc temperature T > 0 (A -> A / T; `calibrate=true`).
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
        temperature: float = 1.0,
    ) -> None:
        if int(chunk_elements) < 1:
            raise ValueError(f"chunk_elements must be a positive integer, got {chunk_elements}")
        temperature = float(temperature)
        if not (math.isfinite(temperature) and temperature > 0):
            raise ValueError(f"temperature must be a finite number > 0, got {temperature}")
        self.temperature = temperature
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
        R, q, dispersion, dt, A, F = (
            torch.cat(values) if values[0] is not None else None
            for values in zip(*parts, strict=True)
        )
        keep = None
        if self.ood is not None and dt is not None and self.ood.get("score") == "dt":
            keep = dt < float(self.ood["threshold"])
        return RotationEstimate(
            R=R, q=q, dispersion=dispersion, dt=dt, keep=keep, A=A, F=F,
            temperature=self.temperature,
        )  # fmt: skip

    def _predict(self, x: Tensor) -> tuple[Tensor | None, ...]:
        """R (b, 3, 3), q (b, 4), dispersion (b, 3), DT (b,), A (b, 4, 4) and F (b, 3, 3) of one
        chunk of inputs, the belief tempered by `temperature` (None where the head has none)."""
        raw = self.net(x.to(self.device, self.dtype))
        if not bool(torch.isfinite(raw).all()):
            raise FloatingPointError("the network output is not finite for these inputs")
        p = self.head(raw).with_temperature(self.temperature)
        return p.R, p.q, p.dispersion, p.dt, p.A, getattr(p, "F", None)


def load(
    ckpt_path: str | os.PathLike,
    device: str | torch.device = "cpu",
    chunk_elements: int = CHUNK_ELEMENTS,
) -> Predictor:
    """Load a rotlearn checkpoint (or a run directory's last one) as a `Predictor`.

    Goes through `rotlearn.checkpoint.load_run`: the file is read with
    `torch.load(weights_only=True)` (pickled code is refused: `UnsafeCheckpointError`) and the
    saved config may only name allowlisted components (`UntrustedConfigError`, naming the key),
    checked before the network and head are rebuilt from it. The belief's temperature fitted
    for this checkpoint (`calibrate=true`: `checkpoints/temperature.json`, read strictly) is
    applied to every estimate.
    """
    require("train", "rotlearn.load (it rebuilds the model from the checkpoint's Hydra config)")
    from omegaconf import OmegaConf

    run = load_run(ckpt_path, task="rotation")
    net, head = run.build("net"), run.build("rep")
    net.load_state_dict(run.weights("net"))
    config = OmegaConf.to_container(run.config)
    return Predictor(
        net, head, config, ood=run.ood, device=device, chunk_elements=chunk_elements,
        temperature=run.temperature,
    )  # fmt: skip
