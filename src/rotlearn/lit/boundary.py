"""The run directory is the boundary of what training writes, deletes and loads.

Lightning restores a `ModelCheckpoint`'s paths from the checkpoint a run resumes from
(`best_model_path`, `best_k_models`, `kth_best_model_path`, `last_model_path`) and later deletes
the "old best" file they name; its check that the file lies in the checkpoint folder does not
normalise `..`. A checkpoint is data someone may have sent, so:

- `checked_checkpoint_states` (called before anything is built, and again by `CheckpointStateGuard`
  while the checkpoint is restored) accepts only paths that name a file the callback itself
  writes (its `filename` template, or `last` for `last_model_path`, with the `.ckpt` extension)
  directly in the folder the state was saved from, and rebases them into the callback's own
  folder (a copied or moved run keeps its best checkpoint); any other path refuses the
  checkpoint, naming it.
- `RunCheckpointIO`, the trainer's checkpoint I/O, writes checkpoints durably (a temporary file
  beside the target, fsynced, renamed: a full disk leaves the previous `last.ckpt` whole and
  loadable), reads them through rotlearn's bounded loader (`rotlearn.checkpoint.load_checkpoint`:
  never unpickled), writes only inside the run or the folders its checkpoint callbacks were
  given (a callback without one put its file name's `..` beside the run), and deletes only
  regular `.ckpt` files inside the run.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
from lightning.fabric.plugins.io.checkpoint_io import CheckpointIO
from lightning.pytorch.callbacks import ModelCheckpoint
from torch import Tensor

from rotlearn.checkpoint import UnsafeCheckpointError, load_checkpoint, save_checkpoint
from rotlearn.lit.state import rng_state_problem

__all__ = [
    "CheckpointStateGuard",
    "RunCheckpointIO",
    "UnsafeCheckpointError",
    "checked_checkpoint_states",
]

log = logging.getLogger("rotlearn")
_PATH_KEYS = ("best_model_path", "kth_best_model_path", "last_model_path")
_SCORE_KEYS = ("best_model_score", "current_score", "kth_value")


def _score(value: Any) -> bool:
    """A monitored value as Lightning keeps it: None, a number or a one-element tensor."""
    if isinstance(value, Tensor):
        return value.numel() == 1
    return value is None or (isinstance(value, int | float) and not isinstance(value, bool))


def _name_pattern(template: str, extension: str) -> re.Pattern:
    """The file names a `ModelCheckpoint` writes from a filename template (`{epoch}` and the
    like: anything; Lightning's `-v<n>` version suffix; the extension)."""
    parts = re.split(r"(\{[^}]*\})", template)
    body = "".join(".+" if p.startswith("{") else re.escape(p) for p in parts)
    return re.compile(body + r"(-v\d+)?" + re.escape(extension))


def _rebased(state: dict[str, Any], callback: ModelCheckpoint, run: Path, where: str) -> dict:
    """A `ModelCheckpoint` state whose paths name files of `callback` (module docstring)."""
    dirpath = Path(callback.dirpath or run / "checkpoints")
    extension = callback.FILE_EXTENSION
    own = {"last_model_path": _name_pattern(callback.CHECKPOINT_NAME_LAST, extension)}
    default = _name_pattern(callback.filename or "{epoch}-{step}", extension)
    saved_dir = state.get("dirpath")
    if saved_dir is not None and not isinstance(saved_dir, str):
        raise UnsafeCheckpointError(f"{where}: dirpath must be a path, got {saved_dir!r}")
    base = os.path.normpath(os.path.abspath(saved_dir or dirpath))

    def rebase(key: str, path: Any) -> str:
        if not isinstance(path, str):
            raise UnsafeCheckpointError(f"{where}: {key} must be a path, got {path!r}")
        if path == "":
            return ""
        name = os.path.relpath(os.path.normpath(os.path.abspath(path)), base)
        ours = own.get(key, default).fullmatch(name)
        if "://" in path or name.startswith("..") or os.sep in name or not ours:
            raise UnsafeCheckpointError(
                f"{where}: {key} names {path!r}, which is not a file this callback writes in "
                f"the state's own checkpoint folder {base}; refusing the checkpoint (Lightning "
                "would load or delete that file)"
            )
        target = dirpath / name
        real = Path(os.path.realpath(target))
        if not real.is_relative_to(run):
            raise UnsafeCheckpointError(
                f"{where}: {key} names {target}, which resolves to {real}, outside the run {run}"
            )
        return str(target)

    out = dict(state)
    for key in _PATH_KEYS:
        if key in state:
            out[key] = rebase(key, state[key])
    models = state.get("best_k_models", {})
    if not isinstance(models, dict):
        raise UnsafeCheckpointError(f"{where}: best_k_models must be a mapping of paths to scores")
    out["best_k_models"] = {rebase("best_k_models", k): v for k, v in models.items()}
    for key, value in [*((k, state.get(k)) for k in _SCORE_KEYS), *models.items()]:
        if not _score(value):
            raise UnsafeCheckpointError(f"{where}: {key} must be a number, got {value!r}")
    out["dirpath"] = str(dirpath)
    return out


def checked_checkpoint_states(
    checkpoint: dict[str, Any],
    callbacks: Iterable[Any],
    run_dir: str | os.PathLike,
    where: str | os.PathLike,
) -> dict[str, Any]:
    """The checkpoint with the state of every `ModelCheckpoint` in `callbacks` checked and its
    paths rebased into that callback's folder (in place; also returned).

    Args:
        checkpoint: as loaded (`rotlearn.checkpoint.load_checkpoint`).
        callbacks: the run's callbacks (others than `ModelCheckpoint` are skipped).
        run_dir: the run directory; every path must resolve inside it.
        where: the checkpoint file, for messages.

    Raises:
        UnsafeCheckpointError: naming the checkpoint, the callback's state and the path at
            fault: a path outside the state's own checkpoint folder, not a `.ckpt` file, not
            local, resolving (symlinks followed) outside the run; or a state of the wrong shape
            (any callback's, the loops', optimizers' and schedulers': `_training_state_problem`).
    """
    states = checkpoint.get("callbacks") or {}
    if not isinstance(states, dict):
        raise UnsafeCheckpointError(f"{where}: callbacks must be a mapping of states")
    if odd := next((str(k) for k, state in states.items() if not isinstance(state, dict)), None):
        raise UnsafeCheckpointError(
            f"{where}: callbacks: the state of {odd[:200]} must be a mapping"
        )
    if (problem := _training_state_problem(checkpoint)) is not None:
        raise UnsafeCheckpointError(f"{where}: {problem}")
    run = Path(os.path.realpath(run_dir))
    for callback in callbacks:
        if not isinstance(callback, ModelCheckpoint) or callback.state_key not in states:
            continue
        here = f"{where}: the {type(callback).__name__} state (monitor {callback.monitor})"
        states[callback.state_key] = _rebased(states[callback.state_key], callback, run, here)
    return checkpoint


def _training_state_problem(checkpoint: dict[str, Any]) -> str | None:
    """What is wrong with the loops', optimizers' and schedulers' states Lightning restores on
    resume (a traceback from inside `fit`, after the run's records had moved, otherwise), or
    None: `loops` a mapping of mappings down to numbers (progress counters), `optimizer_states`
    mappings with a `state` mapping and a `param_groups` list of mappings, `lr_schedulers`
    mappings, `rng_states` what `rotlearn.lit.state.set_rng_states` restores."""
    stack = [("loops", checkpoint.get("loops") or {})]
    while stack:
        key, node = stack.pop()
        if isinstance(node, dict):
            stack.extend((f"{key}.{k}", v) for k, v in node.items())
        elif not (node is None or isinstance(node, int | float)) or key == "loops":
            return f"{key} must be a mapping of loop states down to numbers"
    for i, state in enumerate(checkpoint.get("optimizer_states") or []):
        mapping = state if isinstance(state, dict) else {}
        groups = mapping.get("param_groups")
        if not isinstance(mapping.get("state"), dict) or not (
            isinstance(groups, list) and all(isinstance(g, dict) for g in groups)
        ):
            return f"optimizer_states[{i}] must be a mapping with state and param_groups"
    for i, state in enumerate(checkpoint.get("lr_schedulers") or []):
        if not isinstance(state, dict):
            return f"lr_schedulers[{i}] must be a mapping"
    return rng_state_problem(checkpoint["rng_states"]) if "rng_states" in checkpoint else None


class CheckpointStateGuard(pl.Callback):
    """Checks the checkpoint callbacks' states of a checkpoint being restored
    (`checked_checkpoint_states`) before Lightning hands them to the callbacks: Lightning calls
    every `on_load_checkpoint` before any callback's `load_state_dict`.

    Args:
        run_dir: the run directory.
    """

    def __init__(self, run_dir: str | os.PathLike) -> None:
        self.run_dir = Path(run_dir)

    def on_load_checkpoint(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, checkpoint: dict[str, Any]
    ) -> None:
        checked_checkpoint_states(checkpoint, trainer.callbacks, self.run_dir, trainer.ckpt_path)


class RunCheckpointIO(CheckpointIO):
    """The trainer's checkpoint I/O (module docstring): durable writes inside the run or the
    folders given, rotlearn's bounded loader, and deletion of nothing but the run's own
    checkpoint files.

    Args:
        run_dir: the run directory.
        folders: other folders checkpoints may be written to: those the run's checkpoint
            callbacks were given (`dirpath`; a resumed run's only where its own command line
            set them, `rotlearn.cli.rundir.check_placement`).
    """

    def __init__(
        self, run_dir: str | os.PathLike, folders: Iterable[str | os.PathLike] = ()
    ) -> None:
        self.run_dir = Path(run_dir)
        self.folders = [Path(os.path.realpath(f)) for f in folders if f]

    def save_checkpoint(
        self, checkpoint: dict[str, Any], path: str | os.PathLike, storage_options: Any = None
    ) -> None:
        if storage_options is not None:
            raise TypeError("rotlearn's checkpoint I/O takes no storage_options")
        real = Path(os.path.realpath(Path(path).parent)) / Path(path).name
        allowed = [Path(os.path.realpath(self.run_dir)), *self.folders]
        if not any(real.is_relative_to(folder) for folder in allowed):
            raise UnsafeCheckpointError(
                f"refusing to write {path}: it resolves to {real}, outside the run "
                f"{self.run_dir} and every checkpoint callback's dirpath"
            )
        save_checkpoint(checkpoint, path)

    def load_checkpoint(
        self, path: str | os.PathLike, map_location: Any = None, weights_only: bool | None = None
    ) -> dict[str, Any]:
        return load_checkpoint(path, map_location=map_location)  # always weights only

    def remove_checkpoint(self, path: str | os.PathLike) -> None:
        path = Path(path)
        try:
            is_file = path.is_file() and not path.is_symlink()
        except OSError:
            is_file = False
        real = Path(os.path.realpath(path))
        inside = real.is_relative_to(Path(os.path.realpath(self.run_dir)))
        if not os.path.lexists(path):
            return
        if not (is_file and inside and path.suffix == ".ckpt"):
            log.warning("kept %s: it is not a checkpoint file of the run %s", path, self.run_dir)
            return
        path.unlink()
