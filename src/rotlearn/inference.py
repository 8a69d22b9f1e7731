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

    ensemble = rotlearn.load([run_0, run_1, run_2])   # K separately trained runs (belief heads)
    ensemble.calibrate(val_inputs, val_R)             # its temperature and level map (held out)
    estimate = ensemble(points)         # A = sum of the members' A (the product of their beliefs)
    estimate.disagreement               # (B,) largest angle (deg), a member to the ensemble

The belief (heads that define one: `rep=a`, and the matrix Fisher head, whose `A` is the Bingham
matrix of the same density and whose `F` is carried too) is the Bingham density
p(q; A) = exp(-q^T A q) / Z(A) over unit quaternions (x, y, z, w), antipodally symmetric, so also a
density on SO(3). `log_prob` is w.r.t. the uniform probability measure (the Haar probability on
SO(3), the uniform measure on S^3): a value > 0 means more likely than uniform. When the run was
calibrated (`calibrate`, on by default for heads with a belief), the checkpoint's temperature T
(`checkpoints/temperature.json`) is applied: A, F, the dispersion and the DT score are those of
the calibrated belief A / T (and the OOD keep flags compare that DT with the threshold
calibrated on the same scale).

Credible regions. The highest-density region of mass m is {R : log p(R) >= c_m}, with c_m the
(1 - m)-quantile of log p over the belief's own samples. The calibrated credible region of level
a (the one that holds the truth a fraction a of the time on data like the validation set) is the
HPD region of mass m = `estimate.credible_mass(a)`: the checkpoint's recalibration of the levels
(`rotlearn.bingham.LevelMap`), or m = a without one. Per estimate, by Monte Carlo (error
~ sqrt(m (1 - m) / n) in the mass)::

    draws = estimate.sample(4096)                                       # (B, 4096, 4)
    m = estimate.credible_mass(0.9)                                     # the calibrated 90 %
    c = estimate.log_prob(draws).quantile(1 - float(m), dim=-1)         # (B,) its cut
    inside = estimate.log_prob(R_candidate) >= c                        # (B,) bool: R in the region

The radius of the smallest ball around the mode holding the mass m, in degrees ("m of the belief
lies within r of the rotation"), is `rotlearn.bingham.credible_radius_deg(estimate.A, m)`; with
m = `estimate.credible_mass(a)` it is the calibrated level-a ball (exact where the belief is
isotropic, when balls are its HPD regions; `rotlearn-predict` reports it for a = 0.9).
"""

from __future__ import annotations

import importlib
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from rotlearn import bingham
from rotlearn.checkpoint import load_run
from rotlearn.extras import require
from rotlearn.geometry import rotmat_to_quat
from rotlearn.heads import RotationHead, RotationPrediction

__all__ = [
    "CHUNK_ELEMENTS",
    "Predictor",
    "RotationEstimate",
    "ensemble_members",
    "load",
    "usable_device",
]

# Input numbers sent through the network at once: the Predictor splits larger batches into
# chunks of about this many (at least one sample), so its memory stays bounded for any batch.
CHUNK_ELEMENTS = 2**20
NO_BELIEF = "this model's head defines no belief (only rep=a and the Fisher head do)"


@dataclass(frozen=True)
class RotationEstimate:
    """What a `Predictor` returns for a batch of B inputs.

    Attributes:
        R: (B, 3, 3) rotation matrices.
        q: (B, 4) unit quaternions (x, y, z, w), w >= 0.
        dispersion: (B, 3) Bingham dispersion coefficients (l1 - l4, l1 - l3, l1 - l2) <= 0
            (heads with a belief: rep=a, rep=fisher; more negative = more concentrated belief),
            else None.
        dt: (B,) dispersion-thresholding score tr(Lambda) = 3 l1 - l2 - l3 - l4 (paper eq. 26;
            heads with a belief; lower = more confident), else None.
        keep: (B,) bool, True where the OOD score passes the checkpoint's calibrated threshold,
            or None when the checkpoint carries no threshold.
        A: (B, 4, 4) the Bingham belief p(q) ~ exp(-q^T A q) (paper eqs. 8, 14), tempered
            (A / T), for heads that define a belief, else None.
        F: (B, 3, 3) the matrix Fisher parameter, p(R) ~ exp(tr(F^T R)), tempered (F / T), for
            the Fisher head, else None.
        temperature: the post-hoc temperature T applied (1.0: none).
        level_map: the recalibration of the credible levels (`rotlearn.bingham.LevelMap`), or
            None (`credible_mass`).
        disagreement: (B,) for an ensemble, the largest angle in degrees between a member's
            rotation and the ensemble's (`rotlearn.bingham.disagreement`), else None.

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
    level_map: bingham.LevelMap | None = None
    disagreement: Tensor | None = None

    def credible_mass(self, alpha: float) -> Tensor:
        """The belief mass whose highest-density region is the calibrated credible region of
        level alpha in [0, 1] (module docstring): `level_map.mass(alpha)`, or alpha itself
        without a level map. A 0-dim float64 tensor."""
        if not 0.0 <= float(alpha) <= 1.0:
            raise ValueError(f"alpha must lie in [0, 1], got {alpha}")
        if self.level_map is None:
            return torch.tensor(float(alpha), dtype=torch.float64)
        return self.level_map.mass(float(alpha))

    def _belief(self) -> Tensor:
        if self.A is None:
            raise ValueError(f"{NO_BELIEF}: nothing to sample or score")
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


def _data_method(config: dict[str, Any], name: str) -> Any:
    """Method `name` of the run's datamodule class (`config["data"]["_target_"]`: the config is
    the user's, or passed `trusted_config` when `load` read it from a file), or None (none
    named, or its module needs an extra that is not installed: inputs are then taken as given)."""
    data = config.get("data") if isinstance(config, Mapping) else None
    target = str(data.get("_target_", "")) if isinstance(data, Mapping) else ""
    module, _, attr = target.rpartition(".")
    try:
        found = importlib.import_module(module) if module else None
    except ImportError:
        return None
    return getattr(getattr(found, attr, None), name, None)


class Predictor:
    """A trained network and head, in evaluation mode, that validate what they are given.

    Args:
        net: the backbone; head: the representation head.
        config: the run's resolved config (as saved in the checkpoint).
        ood: optional {"score": "dt", "threshold": float, ...}: the threshold a run's OOD
            evaluation set on its reference pairs (the validation set by default; the run's
            `checkpoints/ood_thresholds.json`).
        temperature: the belief's post-hoc temperature T > 0 (A -> A / T; `calibrate`).
        level_map: the recalibration of the tempered belief's credible levels, or None.
        device: where to run.
        chunk_elements: input numbers per forward pass; larger batches are split into chunks
            of whole samples (at least one), so memory is bounded whatever the batch size. A
            point sample (one cloud pair) of more numbers cannot be split and is refused.
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
        level_map: bingham.LevelMap | None = None,
    ) -> None:
        if int(chunk_elements) < 1:
            raise ValueError(f"chunk_elements must be a positive integer, got {chunk_elements}")
        temperature = float(temperature)
        if not (math.isfinite(temperature) and temperature > 0):
            raise ValueError(f"temperature must be a finite number > 0, got {temperature}")
        self.temperature, self.level_map = temperature, level_map
        self.chunk_elements = int(chunk_elements)
        self.device = usable_device(device)
        self.net = net.to(self.device).eval()
        self.head = head.to(self.device).eval()
        self.config = config or {}
        self.ood = ood
        self.dtype = next(net.parameters()).dtype
        self.in_channels = getattr(net, "in_channels", None)
        self.image_size = (
            getattr(net, "image_size", None) if getattr(net, "channel_axis", -1) == 1 else None
        )
        self.prepare = _data_method(self.config, "prepare_points")  # e.g. unit u_i (synthetic)

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
        if self.image_size is None and inputs.shape[-2:].numel() > self.chunk_elements:
            points, width = inputs.shape[-2:]
            raise ValueError(
                f"a sample of {points} points ({points * width} numbers) is over the "
                f"{self.chunk_elements} numbers a forward pass takes (chunk_elements): "
                "subsample it, or load(..., chunk_elements=...) for more"
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
        if self.image_size is None and self.prepare is not None:
            x = self.prepare(x)  # point inputs as the training data has them
        if x.ndim == (3 if self.image_size is not None else 2):
            x = x.unsqueeze(0)
        per_sample = max(1, x[:1].numel())
        size = max(1, self.chunk_elements // per_sample)
        parts = [self._predict(chunk) for chunk in x.split(size)]
        R, q, dispersion, dt, A, F, disagreement = (
            torch.cat(values) if values[0] is not None else None
            for values in zip(*parts, strict=True)
        )
        keep = None
        if self.ood is not None and dt is not None and self.ood.get("score") == "dt":
            keep = dt < float(self.ood["threshold"])
        return RotationEstimate(
            R=R, q=q, dispersion=dispersion, dt=dt, keep=keep, A=A, F=F,
            temperature=self.temperature, level_map=self.level_map if A is not None else None,
            disagreement=disagreement,
        )  # fmt: skip

    def _predict(self, x: Tensor) -> tuple[Tensor | None, ...]:
        """R (b, 3, 3), q (b, 4), dispersion (b, 3), DT (b,), A (b, 4, 4), F (b, 3, 3) and the
        disagreement (b,) of one chunk of inputs, the belief tempered by `temperature` (None
        where the head has none)."""
        p = self._untempered(x).with_temperature(self.temperature)
        if p.A is not None and not bool(torch.isfinite(p.A).all()):
            raise FloatingPointError(
                f"the belief tempered by the temperature {self.temperature:g} is not finite"
            )
        return p.R, p.q, p.dispersion, p.dt, p.A, p.F, p.disagreement

    def _untempered(self, x: Tensor) -> RotationPrediction:
        raw = self.net(x.to(self.device, self.dtype))
        if not bool(torch.isfinite(raw).all()):
            raise FloatingPointError("the network output is not finite for these inputs")
        return self.head(raw)

    @torch.no_grad()
    def calibrate(self, inputs: Any, targets: Tensor) -> dict[str, float]:
        """Fit this predictor's belief calibration on held-out data, replacing the one it has:
        the temperature T (`rotlearn.bingham.fit_temperature`) and the map of the tempered
        belief's credible levels (`rotlearn.bingham.fit_level_map`), as `calibrate` does after
        training (`rotlearn.lit.calibration`). For an ensemble (`load([run, ...])`), whose
        product belief is over-confident, this is the step that makes it calibrated.

        Args:
            inputs: held-out inputs as `__call__` takes them (not the test data).
            targets: their true rotations (B, 3, 3) or quaternions (B, 4) (x, y, z, w), a
                tensor or numpy array, one per input.

        Returns:
            {"temperature", "nll_before", "nll_after", "num"}.

        Raises:
            ValueError: the head defines no belief, or targets is not one rotation per input.
        """
        if not self.head.defines_belief:
            raise ValueError(f"{NO_BELIEF}: nothing to calibrate")
        x = self._validate(inputs)
        x = x.unsqueeze(0) if x.ndim == (3 if self.image_size is not None else 2) else x
        q = torch.as_tensor(targets).to(torch.float64).cpu()
        if q.shape not in ((len(x), 4), (len(x), 3, 3)):
            raise ValueError(f"targets must be ({len(x)}, 3, 3) rotations or ({len(x)}, 4) "
                             f"quaternions, one per input; got {tuple(q.shape)}")  # fmt: skip
        q = q if q.shape[-1] == 4 else rotmat_to_quat(q)
        size = max(1, self.chunk_elements // max(1, x[:1].numel()))
        A = torch.cat([self._untempered(c).A.double().cpu() for c in x.split(size)])
        fit = bingham.fit_temperature(A, q)
        self.temperature = float(fit.temperature)
        levels = bingham.hpd_level(A / self.temperature, q, 1000, torch.Generator().manual_seed(1))
        self.level_map = bingham.fit_level_map(levels)
        return {"temperature": self.temperature, "nll_before": fit.nll_before,
                "nll_after": fit.nll_after, "num": fit.num}  # fmt: skip


def usable_device(device: str | torch.device) -> torch.device:
    """The torch device `device` names, checked to exist on this machine.

    Raises:
        ValueError: not a device name, or a CUDA device this machine (or this torch) lacks.
    """
    try:
        found = torch.device(device)
    except (RuntimeError, ValueError, TypeError) as exc:
        raise ValueError(f"device {device}: not a device name ({exc})") from None
    if found.type == "cuda" and (found.index or 0) >= (count := torch.cuda.device_count()):
        have = f"{count} CUDA device(s)" if count else "no CUDA device (or a torch without CUDA)"
        raise ValueError(f"device {device}: this machine has {have}; try cpu")
    return found


def load(
    ckpt_path: str | os.PathLike | Sequence[str | os.PathLike],
    device: str | torch.device = "cpu",
    chunk_elements: int = CHUNK_ELEMENTS,
) -> Predictor:
    """Load a rotlearn checkpoint (or a run directory: the weights its test scored) as a
    `Predictor`; a list of them as the `Predictor` of their ensemble.

    An ensemble (K runs with belief heads, trained on the same kind of input, e.g. with other
    seeds) predicts with every member and multiplies their beliefs: A = sum_k A_k / T_k, each
    member tempered by its own calibration (`rotlearn.heads.EnsembleHead`,
    `rotlearn.bingham.product`); estimates carry the members' `disagreement`. The ensemble's own
    temperature starts at 1: fit it on held-out data with `Predictor.calibrate`. The OOD
    thresholds of the members are not used (an ensemble's DT has its own scale).

    Goes through `rotlearn.checkpoint.load_run`: the file is read with
    `torch.load(weights_only=True)` (pickled code is refused: `UnsafeCheckpointError`) and the
    saved config may only name allowlisted components (`UntrustedConfigError`, naming the key),
    checked before the network and head are rebuilt from it; the stored weights are checked
    against the network the config describes, built first on the meta device (names, shapes,
    floating point, finite), so no size named in the file is allocated before it is known to
    match the weights (`SavedRun.build`). The belief's calibration fitted for this checkpoint
    (`calibrate`: `checkpoints/temperature.json`, read strictly: its temperature and level map)
    is applied to every estimate.
    """
    require("train", "rotlearn.load (it rebuilds the model from the checkpoint's Hydra config)")
    from omegaconf import OmegaConf

    device = usable_device(device)  # before anything is read
    if not isinstance(ckpt_path, str | os.PathLike):
        if not isinstance(ckpt_path, Sequence) or not all(
            isinstance(p, str | os.PathLike) for p in ckpt_path
        ):
            raise TypeError(
                "expected a run directory or .ckpt path, or a list of them; got "
                f"{type(ckpt_path).__name__}"
            )
        return _load_ensemble(list(ckpt_path), device, chunk_elements)
    run = load_run(ckpt_path, task="rotation")
    net, head = run.build("net"), run.build("rep", prefix="head")  # weights checked, then loaded
    config = OmegaConf.to_container(run.config)
    return Predictor(
        net, head, config, ood=run.ood, device=device, chunk_elements=chunk_elements,
        temperature=run.temperature, level_map=run.level_map,
    )  # fmt: skip


def ensemble_members(
    paths: Sequence[str | os.PathLike],
) -> tuple[nn.Module, RotationHead, list[Any]]:
    """(EnsembleNet, EnsembleHead, the members' `SavedRun`s) of K runs, each loaded through
    `load_run` (the same checks as `load`), weights and temperatures applied.

    Raises:
        ValueError: no runs, a checkpoint listed twice (its belief would count twice), or a
            member whose head has no belief.
    """
    from rotlearn.heads import EnsembleHead
    from rotlearn.nets import EnsembleNet

    if not paths:
        raise ValueError("an ensemble needs at least one run")
    _refuse_repeats(paths, [os.path.realpath(p) for p in paths])  # before loading any
    runs = [load_run(p, task="rotation") for p in paths]
    _refuse_repeats(paths, [os.path.realpath(run.path) for run in runs])  # a run and its file
    nets, heads = [], []
    for run in runs:
        net, head = run.build("net"), run.build("rep", prefix="head")  # weights checked, loaded
        if not head.defines_belief:
            raise ValueError(f"{run.path}: rep={head.name} has no belief; an ensemble needs one")
        nets.append(net.eval())
        heads.append(head)
    head = EnsembleHead(heads, [run.temperature for run in runs])
    return EnsembleNet(nets), head, runs


def _refuse_repeats(paths: Sequence[str | os.PathLike], files: list[str]) -> None:
    """ValueError for a member listed again (`files[i]`: what `paths[i]` names, resolved): its
    belief would count twice."""
    for later, file in enumerate(files):
        if (first := files.index(file)) < later:
            raise ValueError(f"{paths[later]} is {paths[first]} again ({file}): each member of "
                             "an ensemble must be another run")  # fmt: skip


def _load_ensemble(
    paths: list[str | os.PathLike], device: str | torch.device, chunk_elements: int
) -> Predictor:
    from omegaconf import OmegaConf

    net, head, runs = ensemble_members(paths)
    config = OmegaConf.to_container(runs[0].config)
    return Predictor(net, head, config, device=device, chunk_elements=chunk_elements)
