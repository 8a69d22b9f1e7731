"""Floor 1: representation heads, stateless maps from a network output to a rotation (`rep=`).

Every module of this package is imported here, so a new head is one module (a `RotationHead`
subclass decorated with `@register_head`) and one `conf/rep/<name>.yaml`; nothing else changes.
"""

import importlib
import pkgutil

from rotlearn.heads.base import (
    HEADS,
    RotationHead,
    RotationPrediction,
    make_head,
    register_head,
)
from rotlearn.heads.ensemble import EnsembleHead
from rotlearn.heads.fisher import FisherHead
from rotlearn.heads.quat import QuatHead
from rotlearn.heads.sixd import SixDHead
from rotlearn.heads.svd import SVD9DHead
from rotlearn.heads.symmetric import AHead, a_min_eigvec

__all__ = [
    "HEADS",
    "AHead",
    "EnsembleHead",
    "FisherHead",
    "QuatHead",
    "RotationHead",
    "RotationPrediction",
    "SVD9DHead",
    "SixDHead",
    "a_min_eigvec",
    "make_head",
    "register_head",
]

for _module in pkgutil.iter_modules(__path__):  # registers every head defined in this package
    importlib.import_module(f"{__name__}.{_module.name}")
