"""Reading checkpoints safely: tensors and plain data only, never arbitrary pickled code."""

from __future__ import annotations

import os
import pickle
from pathlib import Path
from typing import Any

import torch

__all__ = ["UnsafeCheckpointError", "load_checkpoint", "resolve_checkpoint"]


class UnsafeCheckpointError(pickle.UnpicklingError):
    """The file holds pickled objects beyond tensors and plain data; it was not unpickled."""


def resolve_checkpoint(path: str | os.PathLike) -> Path:
    """A checkpoint file, or a run directory (meaning its checkpoints/last.ckpt)."""
    path = Path(path)
    if path.is_dir():
        path = path / "checkpoints" / "last.ckpt"
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    return path


def load_checkpoint(path: str | os.PathLike, map_location: Any = "cpu") -> dict[str, Any]:
    """`torch.load(path, weights_only=True)`: refuses, without running it, any pickled payload.

    Args:
        path: a `.ckpt` file or a run directory.
        map_location: as in `torch.load`.

    Raises:
        FileNotFoundError: no such checkpoint.
        UnsafeCheckpointError: the file carries objects that only a full unpickler could build
            (such a file can run arbitrary code when loaded; rotlearn never loads it).
    """
    path = resolve_checkpoint(path)
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        reason = next((line for line in str(exc).splitlines() if "GLOBAL" in line), str(exc))
        raise UnsafeCheckpointError(
            f"refusing to load {path}: it contains pickled Python objects, not only tensors and "
            f"plain data ({reason.strip()}). Loading it could run arbitrary code; rotlearn only "
            "reads checkpoints with torch.load(weights_only=True)."
        ) from None
