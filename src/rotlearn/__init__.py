"""rotlearn: deep rotation learning with uncertainty.

Quaternions are scalar LAST everywhere: q = (x, y, z, w), Hamilton product, active rotations.
"""

from typing import TYPE_CHECKING

__version__ = "0.1.0"

if TYPE_CHECKING:
    from rotlearn.inference import Predictor


def load(ckpt_path, device="cpu", **kwargs) -> "Predictor":
    """Load a checkpoint (or a run directory) as a `rotlearn.inference.Predictor`; keyword
    arguments as `rotlearn.inference.load` (e.g. `chunk_elements`).

    Imported lazily so that `import rotlearn` stays light.
    """
    from rotlearn.inference import load as _load

    return _load(ckpt_path, device=device, **kwargs)
