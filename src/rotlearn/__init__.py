"""rotlearn: deep rotation learning with uncertainty.

Quaternions are scalar LAST everywhere: q = (x, y, z, w), Hamilton product, active rotations.

The top level re-exports the drop-in layers (`rotlearn.nn`), the one-call functional maps
(`rotlearn.geometry`) and `load`. They are imported on first use (module `__getattr__`), so
`import rotlearn` costs nothing beyond itself and needs only torch and numpy.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"  # the one source of the version: pyproject.toml reads it (hatch)

# public name -> the module that defines it (imported on first access)
_LAZY = {
    "ALayer": "rotlearn.nn",
    "SymmetricMatrixToQuat": "rotlearn.nn",
    "SixDToRotmat": "rotlearn.nn",
    "SVDToRotmat": "rotlearn.nn",
    "symmatrixvec_to_quat": "rotlearn.geometry",
    "sixd_to_rotmat": "rotlearn.geometry",
    "special_orthogonalize": "rotlearn.geometry",
}

__all__ = ["__version__", "load", *_LAZY]

if TYPE_CHECKING:  # what static tools see; at run time __getattr__ imports these on first use
    from rotlearn.geometry import (  # noqa: F401
        sixd_to_rotmat,
        special_orthogonalize,
        symmatrixvec_to_quat,
    )
    from rotlearn.inference import Predictor
    from rotlearn.nn import ALayer, SixDToRotmat, SVDToRotmat, SymmetricMatrixToQuat  # noqa: F401


def load(ckpt_path, device="cpu", **kwargs) -> Predictor:
    """Load a checkpoint (or a run directory) as a `rotlearn.inference.Predictor`.

    Keyword arguments as `rotlearn.inference.load` (e.g. `chunk_elements`). Rebuilding a model
    from its saved Hydra config needs the training extra: ``pip install 'rotlearn[train]'``.
    """
    from rotlearn.inference import load as _load

    return _load(ckpt_path, device=device, **kwargs)


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'rotlearn' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later look-ups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
