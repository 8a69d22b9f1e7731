"""What every rotlearn LightningModule keeps in its checkpoints: the run's config and the random
states, as tensors and plain data (so `torch.load(weights_only=True)` reads them)."""

from __future__ import annotations

import random
from typing import Any

import numpy as np
import torch

from rotlearn.checkpoint import UnsafeCheckpointError

__all__ = ["RunStateHooks", "rng_state_problem", "rng_states", "set_rng_states"]


class RunStateHooks:
    """Mixin for LightningModules: stores `run_config` (when set) as `rotlearn_config`, and the
    global random states, in every checkpoint; restores the random states on resume, the CPU
    ones all or none (a state that cannot be restored is refused, `rng_state_problem`, whatever
    loads the checkpoint: a resume, Lightning's requeue, a user's own `fit`; the CUDA ones are
    checked for their type only); knows the epochs its weights under test trained
    (`tested_epochs`)."""

    run_config: dict[str, Any] | None = None
    _loaded_for_test: int | None = None  # the epochs of the checkpoint a test loaded

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        if self.run_config is not None:
            checkpoint["rotlearn_config"] = self.run_config
        checkpoint["rng_states"] = rng_states()

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        trainer = getattr(self, "_trainer", None)  # none in `load_from_checkpoint`
        if "rng_states" in checkpoint:  # checked here: Lightning calls this hook first
            if (problem := rng_state_problem(checkpoint["rng_states"])) is not None:
                where = getattr(trainer, "ckpt_path", None) or "the checkpoint"
                raise UnsafeCheckpointError(f"{where}: {problem}")
            set_rng_states(checkpoint["rng_states"])
        testing = trainer is not None and trainer.state.fn == "test" and "epoch" in checkpoint
        self._loaded_for_test = int(checkpoint["epoch"]) + 1 if testing else None  # 0-based

    def on_fit_start(self) -> None:
        self._loaded_for_test = None  # the weights change from here on

    @property
    def tested_epochs(self) -> int:
        """The epochs the weights a test scores trained: the checkpoint's the test loaded
        (`test_ckpt=best`), else the trainer's (the weights in memory; 0 where they were loaded
        outside the trainer, as rotlearn-eval does). A test's results are drawn at this step,
        as the epoch series are (`TensorBoardRunLogger`)."""
        return self._loaded_for_test or self.current_epoch


def rng_states(cuda: bool = True) -> dict[str, Any]:
    """The global random states (torch CPU and, with `cuda`, CUDA; numpy, python) as tensors
    and plain data, so that a checkpoint holding them still loads with
    `torch.load(weights_only=True)`."""
    version, words, gauss = random.getstate()
    name, keys, pos, has_gauss, cached = np.random.get_state()  # noqa: NPY002 (global state)
    states: dict[str, Any] = {
        "torch": torch.get_rng_state(),
        "python": [version, list(words), gauss],
        "numpy": [name, torch.from_numpy(keys.astype(np.int64)), pos, has_gauss, cached],
    }
    if cuda and torch.cuda.is_available():
        states["cuda"] = torch.cuda.get_rng_state_all()
    return states


def set_rng_states(states: dict[str, Any]) -> None:
    """Restore what `rng_states` returned."""
    torch.set_rng_state(states["torch"])
    version, words, gauss = states["python"]
    random.setstate((version, tuple(words), gauss))
    name, keys, pos, has_gauss, cached = states["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), pos, has_gauss, cached))  # noqa: NPY002
    if "cuda" in states and torch.cuda.is_available():  # the devices this process sees
        torch.cuda.set_rng_state_all(states["cuda"][: torch.cuda.device_count()])


def rng_state_problem(states: Any) -> str | None:
    """Why a checkpoint's `rng_states` cannot be restored (a traceback from inside `fit`, after a
    resume had moved the run's records, otherwise), or None: the CPU ones are set, then this
    process's own put back; the CUDA ones are checked for their type only (setting them would
    start CUDA before a forking launcher; a run saved on more devices restores those it sees)."""
    if not isinstance(states, dict):
        return "rng_states must be a mapping"
    cuda = states.get("cuda", [])  # checked, not set: that would start CUDA in this process
    if not isinstance(cuda, list | tuple) or not all(
        isinstance(t, torch.Tensor) and t.dtype == torch.uint8 and t.ndim == 1 for t in cuda
    ):
        return "rng_states.cuda must be a list of byte tensors, one per device"
    current = rng_states(cuda=False)
    try:
        set_rng_states({k: v for k, v in states.items() if k != "cuda"})
    except Exception as exc:  # TypeError, ValueError, KeyError, RuntimeError: whatever it is
        lines = str(exc).strip().splitlines()
        return f"rng_states cannot be restored ({type(exc).__name__}: {lines[0] if lines else ''})"
    finally:
        set_rng_states(current)
    return None
