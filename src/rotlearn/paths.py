"""Where rotlearn's Hydra configs live."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["config_dir"]


def config_dir() -> Path:
    """The `conf/` directory: $ROTLEARN_CONFIG_DIR, the copy inside an installed wheel, or the
    repository's own `conf/` for an editable install."""
    if env := os.environ.get("ROTLEARN_CONFIG_DIR"):
        return Path(env).resolve()
    here = Path(__file__).resolve().parent
    for candidate in (here / "conf", here.parents[1] / "conf"):
        if (candidate / "train.yaml").is_file():
            return candidate
    raise FileNotFoundError(
        "rotlearn's configs were not found: set ROTLEARN_CONFIG_DIR to the repository's conf/"
    )
