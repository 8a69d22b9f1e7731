"""Optional dependencies: which pip extra brings which library; a clear error when one is missing.

`pip install rotlearn` installs only torch and numpy: `rotlearn.geometry`, `rotlearn.heads`,
`rotlearn.bingham`, `rotlearn.losses`, `rotlearn.nets` and `rotlearn.nn` need nothing else. The
training stack (`rotlearn.lit`, `rotlearn.config`, `rotlearn.cli`, `rotlearn.data`'s DataModules,
`rotlearn.ood`, `rotlearn.metrics`, loading a checkpoint) comes with
``pip install 'rotlearn[train]'``; image and mesh datasets with ``pip install 'rotlearn[data]'``;
the A layer's Triton kernels for CUDA with ``pip install 'rotlearn[gpu]'``.
A module that needs an extra calls `require` before importing it, so a bare install says what to
install instead of "No module named ...".
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

__all__ = ["EXTRAS", "MissingExtraError", "import_extra", "require"]

# extra -> the import names it provides (pyproject.toml's [project.optional-dependencies])
EXTRAS: dict[str, tuple[str, ...]] = {
    "train": (
        "lightning",
        "hydra",
        "omegaconf",
        "yaml",
        "torchmetrics",
        "tensorboard",
        "matplotlib",
        "pandas",
        "pydantic",
    ),
    "data": ("cv2", "trimesh", "skimage", "tqdm"),
    "gpu": ("triton",),
}


class MissingExtraError(ModuleNotFoundError):
    """A library of a pip extra is not installed; the message names the extra to install."""


def _message(extra: str, missing: list[str], needed_by: str) -> str:
    return (
        f"{needed_by} needs the '{extra}' extra ({', '.join(missing)} not installed): "
        f"pip install 'rotlearn[{extra}]'"
    )


def require(extra: str, needed_by: str) -> None:
    """Raise `MissingExtraError` naming `extra` when any of its libraries is not installed.

    Looks the libraries up without importing them (`importlib.util.find_spec`), so a module can
    call this first thing and stay as cheap to import as before.

    Args:
        extra: a key of `EXTRAS` ("train" or "data").
        needed_by: what needs it, for the message (e.g. "rotlearn-train").
    """
    missing = [name for name in EXTRAS[extra] if importlib.util.find_spec(name) is None]
    if missing:
        raise MissingExtraError(_message(extra, missing, needed_by), name=missing[0])


def import_extra(name: str, needed_by: str) -> ModuleType:
    """Import the module `name` of an extra; if absent, raise `MissingExtraError` naming the extra.

    Args:
        name: the import name, e.g. "cv2" or "skimage.data".
        needed_by: what needs it, for the message.
    """
    top = name.partition(".")[0]
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as error:
        if error.name is None or error.name.partition(".")[0] != top:
            raise  # the library is there but something it imports is not: not ours to rename
        extra = next((key for key, names in EXTRAS.items() if top in names), None)
        if extra is None:
            raise
        raise MissingExtraError(_message(extra, [top], needed_by), name=top) from error
