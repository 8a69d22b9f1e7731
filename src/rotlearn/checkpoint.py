"""Reading checkpoints and run directories safely: the one loader every rebuild goes through.

A checkpoint is read with `torch.load(weights_only=True)` (tensors and plain data, never pickled
code), and the run config it carries is checked against rotlearn's allowlist of buildable
components (`rotlearn.trust`) before anything is built from it. `rotlearn.load`, `rotlearn-predict`,
`rotlearn-eval` and the OOD evaluation's auto-encoder all load through `load_run`.

The OOD evaluation's calibrated threshold lives beside the checkpoints, in
`<run>/checkpoints/ood_thresholds.json` ({"score": str, "threshold": number, "q": number});
`load_run` reads it (strictly: it is data from a run directory, not trusted) when present.

The belief's post-hoc temperature (`calibrate=true`, `rotlearn.lit.calibration`) lives there too,
in `<run>/checkpoints/temperature.json` ({"temperature": number > 0, "checkpoint": the file name
of the checkpoint it was fitted for, "val_nll", "val_nll_uncalibrated": number or null,
"num_val": int}); `load_run` reads it as strictly and applies it (`SavedRun.temperature`) only to
the checkpoint it names.
"""

from __future__ import annotations

import json
import logging
import math
import os
import pickle
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from rotlearn.extras import require
from rotlearn.paths import checkpoint_file
from rotlearn.trust import UntrustedConfigError, trusted_config

__all__ = [
    "TEMPERATURE_FILE",
    "THRESHOLDS_FILE",
    "SavedRun",
    "UnsafeCheckpointError",
    "UntrustedConfigError",
    "checkpoint_temperature",
    "load_checkpoint",
    "load_run",
    "read_temperature",
    "read_thresholds",
    "resolve_checkpoint",
]

THRESHOLDS_FILE = "ood_thresholds.json"  # beside the checkpoints it calibrates
TEMPERATURE_FILE = "temperature.json"  # beside the checkpoint whose belief it tempers
_MAX_RECORD_BYTES = 4096  # either file is a few dozen bytes; anything larger is refused unread

log = logging.getLogger("rotlearn")


class UnsafeCheckpointError(pickle.UnpicklingError, ValueError):
    """The file is not a checkpoint of tensors and plain data; it was not unpickled."""


def resolve_checkpoint(path: str | os.PathLike) -> Path:
    """A checkpoint file, or a run directory (meaning its checkpoints/last.ckpt): see
    `rotlearn.paths.checkpoint_file` (a sweep directory or another folder is refused, naming
    what to pass instead)."""
    return checkpoint_file(path)


def load_checkpoint(path: str | os.PathLike, map_location: Any = "cpu") -> dict[str, Any]:
    """`torch.load(path, weights_only=True)`: refuses, without running it, any pickled payload.

    Args:
        path: a `.ckpt` file or a run directory.
        map_location: as in `torch.load`.

    Raises:
        FileNotFoundError: no such checkpoint.
        UnsafeCheckpointError: the file is not a dict of tensors and plain data: it carries
            objects that only a full unpickler could build (such a file can run code when
            loaded; rotlearn never loads it), or it is no checkpoint at all.
    """
    path = resolve_checkpoint(path)
    try:
        checkpoint = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        reason = next((line for line in str(exc).splitlines() if "GLOBAL" in line), "")
        detail = f" ({reason.strip()})" if reason else ""
        raise UnsafeCheckpointError(
            f"refusing to load {path}: it is not a checkpoint of tensors and plain data"
            f"{detail}. A file that needs a full unpickler can run code when loaded; rotlearn "
            "only reads checkpoints with torch.load(weights_only=True)."
        ) from None
    except Exception as exc:  # a damaged or foreign file fails in many ways (KeyError, ...)
        text = str(exc).strip()
        first = text.splitlines()[0] if text else ""
        if "weights_only" in first:  # never pass on torch's advice to unpickle
            first = ""
        raise UnsafeCheckpointError(
            f"{path} is not a readable PyTorch checkpoint ({type(exc).__name__}"
            + (f": {first}" if first else "")
            + ")"
        ) from None
    if not isinstance(checkpoint, dict):
        raise UnsafeCheckpointError(
            f"{path} is not a checkpoint: it holds a {type(checkpoint).__name__}, not a dict"
        )
    return checkpoint


@dataclass(frozen=True)
class SavedRun:
    """A trained run as read from its checkpoint, safe to rebuild.

    Attributes:
        path: the checkpoint file.
        config: the run's resolved config (a `DictConfig`): no interpolations, and every
            `_target_` on rotlearn's allowlist.
        state_dict: the LightningModule's weights, name -> tensor.
        ood: the calibrated OOD threshold written by the OOD evaluation beside the checkpoint
            (`THRESHOLDS_FILE`), {"score": str, "threshold": float, "q": float}, or None.
        temperature: the belief's post-hoc temperature T (A -> A / T) fitted for this
            checkpoint (`TEMPERATURE_FILE`); 1.0 without one, or when the file names another
            checkpoint.
    """

    path: Path
    config: Any
    state_dict: dict[str, Tensor]
    ood: dict[str, Any] | None = field(default=None)
    temperature: float = 1.0

    @property
    def task(self) -> str:
        """ "rotation" or "autoencoder": the `task` of the saved model's class (`model._target_`,
        already on the allowlist), or the `task` key of configs saved before the model group."""
        from hydra.utils import get_class
        from omegaconf import OmegaConf

        target = OmegaConf.select(self.config, "model._target_")
        if target is None:
            return str(self.config.get("task", "rotation"))
        return str(getattr(get_class(target), "task", "unknown"))

    def build(self, key: str) -> Any:
        """Instantiate the config node `key` (e.g. "net", "rep")."""
        from hydra.utils import instantiate
        from omegaconf import OmegaConf

        node = OmegaConf.select(self.config, key)
        if node is None:
            raise ValueError(f"{self.path}: the saved config has no {key!r} node")
        return instantiate(node)

    def weights(self, prefix: str) -> dict[str, Tensor]:
        """The weights of the submodule `prefix` (e.g. "net"), with the prefix removed."""
        start = f"{prefix}."
        return {k[len(start) :]: v for k, v in self.state_dict.items() if k.startswith(start)}


def _number(value: Any) -> bool:
    """A finite JSON number (not a bool; an integer too large for a float is not finite)."""
    if not isinstance(value, int | float) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _read_record(path: Path, what: str) -> Any:
    """The JSON in `path` (a small record file), refusing a large file unread, NaN and the
    infinities, and nesting too deep to parse; ValueError naming the file otherwise."""
    if path.stat().st_size > _MAX_RECORD_BYTES:
        raise ValueError(f"{path}: too large for a JSON {what} (at most {_MAX_RECORD_BYTES} bytes)")

    def refuse(constant: str) -> None:
        raise ValueError(f"{constant} is not a number")

    try:
        return json.loads(path.read_text(encoding="utf-8"), parse_constant=refuse)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a JSON {what} ({exc})") from None
    except RecursionError:
        raise ValueError(f"{path}: not a JSON {what} (nested too deeply)") from None


def _check_ood(ood: Any, path: Path, what: str) -> dict[str, Any]:
    """`ood` if it is exactly {score: str, threshold: finite number, q: number in [0, 1]}."""
    expected = "{score: str, threshold: number, q: number in [0, 1]}"
    if not isinstance(ood, dict) or set(ood) != {"score", "threshold", "q"}:
        keys = sorted(map(str, ood)) if isinstance(ood, dict) else type(ood).__name__
        raise ValueError(f"{path}: {what} must be {expected}, got {keys}")
    if not isinstance(ood["score"], str) or not ood["score"]:
        raise ValueError(f"{path}: {what}'s score must be a name, got {ood['score']!r}")
    for key in ("threshold", "q"):
        if not _number(ood[key]):
            raise ValueError(f"{path}: {what}'s {key} must be a finite number, got {ood[key]!r}")
    if not 0.0 <= ood["q"] <= 1.0:
        raise ValueError(f"{path}: {what}'s q must lie in [0, 1], got {ood['q']!r}")
    return {"score": ood["score"], "threshold": float(ood["threshold"]), "q": float(ood["q"])}


def read_thresholds(path: str | os.PathLike) -> dict[str, Any] | None:
    """The calibrated OOD threshold in `path` (a `THRESHOLDS_FILE`), or None if there is none.

    Raises:
        ValueError: the file is not JSON of exactly {score: str, threshold: number, q: number in
            [0, 1]} (the message names the file).
    """
    path = Path(path)
    if not path.is_file():
        return None
    ood = _read_record(path, "OOD threshold file")
    return _check_ood(ood, path, "the OOD threshold")


_TEMPERATURE_KEYS = {"temperature", "checkpoint", "val_nll", "val_nll_uncalibrated", "num_val"}


def read_temperature(path: str | os.PathLike) -> dict[str, Any] | None:
    """The post-hoc temperature record in `path` (a `TEMPERATURE_FILE`), or None if there is none.

    Returns:
        {"temperature": float > 0, "checkpoint": str (a file name), "val_nll": float,
        "val_nll_uncalibrated": float or None, "num_val": int >= 1}.

    Raises:
        ValueError: the file is larger than 4096 bytes, not JSON, holds NaN or an infinity, lacks
            or adds a key, or holds a temperature that is not a finite number > 0 (with a finite
            1 / T), a checkpoint that is not a plain file name, or a count that is not a positive
            integer; the message names the file. Nothing is half-read: the record is checked
            whole before it is returned.
    """
    path = Path(path)
    if not path.is_file():
        return None
    record = _read_record(path, "temperature file")
    expected = (
        "{temperature: number > 0, checkpoint: file name, val_nll: number, "
        "val_nll_uncalibrated: number or null, num_val: int}"
    )
    if not isinstance(record, dict) or set(record) != _TEMPERATURE_KEYS:
        keys = sorted(map(str, record)) if isinstance(record, dict) else type(record).__name__
        raise ValueError(f"{path}: the temperature record must be {expected}, got {keys}")
    t = record["temperature"]
    if not _number(t) or not t > 0 or not math.isfinite(1.0 / float(t)):
        raise ValueError(f"{path}: temperature must be a finite number > 0, got {t!r}")
    name = record["checkpoint"]
    if not isinstance(name, str) or not name or Path(name).name != name or name in (".", ".."):
        raise ValueError(f"{path}: checkpoint must be a checkpoint's file name, got {name!r}")
    for key in ("val_nll", "val_nll_uncalibrated"):
        value = record[key]
        if not _number(value) and not (key == "val_nll_uncalibrated" and value is None):
            raise ValueError(f"{path}: {key} must be a finite number, got {value!r}")
    count = record["num_val"]
    if not isinstance(count, int) or isinstance(count, bool) or count < 1:
        raise ValueError(f"{path}: num_val must be a positive integer, got {count!r}")
    before = record["val_nll_uncalibrated"]
    return {
        "temperature": float(t),
        "checkpoint": name,
        "val_nll": float(record["val_nll"]),
        "val_nll_uncalibrated": None if before is None else float(before),
        "num_val": count,
    }


def checkpoint_temperature(ckpt: Path) -> float:
    """The temperature fitted for the checkpoint file `ckpt` (`read_temperature` of the
    `TEMPERATURE_FILE` beside it): 1.0 without one, and 1.0 with a logged warning when the file
    was fitted for another checkpoint (e.g. best.ckpt's temperature while loading last.ckpt).

    Raises:
        ValueError: as `read_temperature`.
    """
    record = read_temperature(ckpt.parent / TEMPERATURE_FILE)
    if record is None:
        return 1.0
    if record["checkpoint"] != ckpt.name:
        log.warning(
            "%s: the temperature %.4g was fitted for %s, not %s; the belief is left untempered "
            "(T = 1)",
            ckpt.parent / TEMPERATURE_FILE, record["temperature"], record["checkpoint"], ckpt.name,
        )  # fmt: skip
        return 1.0
    return record["temperature"]


def load_run(path: str | os.PathLike, task: str | None = None) -> SavedRun:
    """Read a rotlearn checkpoint (or a run directory's last one) for rebuilding its model.

    Args:
        path: a `.ckpt` file or a run directory.
        task: if given, the run's `task` must be this ("rotation" or "autoencoder").

    Raises:
        FileNotFoundError: no such checkpoint.
        UnsafeCheckpointError: the file carries pickled code or is no checkpoint.
        UntrustedConfigError: the saved config names a `_target_` off the allowlist, or holds an
            interpolation; the message names the key path. Nothing was built.
        ValueError: not a rotlearn checkpoint, or of another task.
    """
    require("train", "load_run (a checkpoint's model is rebuilt from its Hydra config)")
    ckpt = resolve_checkpoint(path)
    checkpoint = load_checkpoint(ckpt)
    saved = checkpoint.get("rotlearn_config")
    if not saved:
        raise ValueError(f"{ckpt} is not a rotlearn checkpoint (no saved config)")
    config = trusted_config(saved, source=ckpt)
    state_dict = checkpoint.get("state_dict")
    if not isinstance(state_dict, dict) or not all(
        isinstance(k, str) and isinstance(v, Tensor) for k, v in state_dict.items()
    ):
        raise ValueError(f"{ckpt}: state_dict must map names to tensors")
    ood = read_thresholds(ckpt.parent / THRESHOLDS_FILE)
    if ood is None and checkpoint.get("rotlearn_ood") is not None:  # runs calibrated in place
        ood = _check_ood(checkpoint["rotlearn_ood"], ckpt, "rotlearn_ood")
    run = SavedRun(ckpt, config, state_dict, ood, checkpoint_temperature(ckpt))
    if task is not None and run.task != task:
        raise ValueError(f"{ckpt} is a task={run.task!r} checkpoint, not task={task!r}")
    return run
