"""OmegaConf resolvers used by the configs, registered on import of `rotlearn.config` (which
rotlearn's Hydra plugin imports wherever Hydra composes conf/, and `rotlearn.cli` too)."""

from __future__ import annotations

import math

import numpy as np
from omegaconf import OmegaConf

__all__ = ["MAX_TRIALS", "gpu_precision", "loguniform_trial", "register_resolvers"]

MAX_TRIALS = 1_000_000  # trials of one sweep (a config read from a run cannot ask for more memory)


def loguniform_trial(trial: int, trials: int, seed: int, low: float, high: float) -> float:
    """The value of trial `trial` of `trials` in a reproducible log-uniform sweep over [low, high).

    Stratified: the log range is cut into `trials` equal slices, a seed-fixed permutation gives each
    trial its own slice, and a seed-fixed uniform draw places it inside. So every sweep covers the
    range evenly, each value is log-uniform, and a trial gets the same value in every sweep with
    the same seed (whatever else is swept beside it).
    """
    trial, trials, seed = int(trial), int(trials), int(seed)
    low, high = float(low), float(high)
    if trials > MAX_TRIALS:  # the permutation below holds `trials` numbers
        raise ValueError(f"trials must be at most {MAX_TRIALS}, got {trials}")
    if not 0 <= trial < trials:
        raise ValueError(f"trial must lie in [0, {trials}), got {trial}")
    if not 0 < low < high:
        raise ValueError(f"need 0 < low < high, got [{low}, {high})")
    slot = np.random.default_rng([seed, trials]).permutation(trials)[trial]
    offset = np.random.default_rng([seed, trials, trial]).random()
    log_low, log_high = math.log(low), math.log(high)
    return float(math.exp(log_low + (slot + offset) / trials * (log_high - log_low)))


def gpu_precision() -> str:
    """The Trainer precision for this machine's GPU (`trainer=gpu`): "bf16-mixed" where the GPU
    has bfloat16 arithmetic (compute capability 8.0 and newer: A100, H100, RTX 30xx/40xx),
    "16-mixed" (float16 with loss scaling) on older GPUs, "32-true" without a GPU."""
    import torch

    if not torch.cuda.is_available():
        return "32-true"
    return "bf16-mixed" if torch.cuda.is_bf16_supported(including_emulation=False) else "16-mixed"


def register_resolvers() -> None:
    """Make `${rl.loguniform:trial,trials,seed,low,high}` and `${rl.gpu_precision:}` available to
    every config."""
    OmegaConf.register_new_resolver("rl.loguniform", loguniform_trial, replace=True)
    OmegaConf.register_new_resolver("rl.gpu_precision", gpu_precision, replace=True)


register_resolvers()
