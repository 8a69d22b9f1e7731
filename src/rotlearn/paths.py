"""Where rotlearn's Hydra configs live, and which checkpoint a command line names."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = [
    "CSV_LOG",
    "EVALUATED_FILE",
    "HISTORY_DIR",
    "OOD_EXAMPLES_FILE",
    "TESTED_WEIGHTS",
    "checkpoint_file",
    "config_dir",
    "earlier_attempts",
]

SWEEP_FILES = ("multirun.yaml", "jobs.json", "planned_jobs.json")  # what Hydra and rotlearn write
# In an evaluation's directory (rotlearn-eval): the run config it evaluated, which rotlearn-report
# reads in place of the evaluation's own config.
EVALUATED_FILE = "evaluated.yaml"
# A run's own figure (the OOD evaluation's example pairs): a report's plot never takes its name.
OOD_EXAMPLES_FILE = "ood_examples.png"
# A run's earlier records, one folder per resume (<run>/history/<n>/: rotlearn.cli.resume).
HISTORY_DIR = "history"
# logger=csv's per-epoch log in a run (conf/logger/csv.yaml); a resume keeps the earlier one.
CSV_LOG = "csv/metrics.csv"
# The weights a run's test scores (`test_ckpt`; metrics.json's `tested_weights`), in words.
TESTED_WEIGHTS = {"last": "the last epoch's", "best": "the best validation epoch's"}


def earlier_attempts(run_dir: str | os.PathLike) -> list[Path]:
    """The folders of a run's earlier attempts, `<run>/HISTORY_DIR/<n>/`, in n's order (names of
    ASCII digits only); none where the run has no history folder. Looks at the file system only."""
    history = Path(run_dir) / HISTORY_DIR
    if not history.is_dir():
        return []
    numbered = (p for p in history.iterdir() if p.name.isascii() and p.name.isdigit())
    return sorted(numbered, key=lambda p: int(p.name))


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


def checkpoint_file(path: str | os.PathLike) -> Path:
    """The checkpoint a command line names: a file as it is, a run directory's
    `checkpoints/last.ckpt`. Looks at the file system only (nothing is read or imported).

    Raises:
        FileNotFoundError: saying what `path` is instead: nothing, a sweep directory or a folder
            of runs such as outputs/ (naming the runs up to three folders below it, one of
            which to pass), or a folder that holds no rotlearn run.
    """
    path = Path(path)
    if not path.is_dir():
        if not path.is_file():
            raise FileNotFoundError(f"no checkpoint at {path}")
        return path
    last = path / "checkpoints" / "last.ckpt"
    if last.is_file():
        return last
    sweep = any((path / name).is_file() for name in SWEEP_FILES)
    below = ("*/" * depth for depth in range(1, 2 if sweep else 4))  # outputs/multirun/<t>/<job>
    jobs = sorted(
        p.parent.parent for glob in below for p in path.glob(f"{glob}checkpoints/last.ckpt")
    )
    if jobs:
        shown = ", ".join(str(job) for job in jobs[:8])
        more = f" and {len(jobs) - 8} more" if len(jobs) > 8 else ""
        what = "is a sweep directory, not one run: pass one of its jobs" if sweep else \
            "holds runs, not one run: pass one of them"  # fmt: skip
        raise FileNotFoundError(f"{path} {what}, {shown}{more}")
    if sweep:
        raise FileNotFoundError(f"{path} is a sweep directory; none of its jobs has a checkpoint")
    raise FileNotFoundError(
        f"{path} is not a rotlearn run: it has no checkpoints/last.ckpt (pass a run directory, "
        "e.g. outputs/runs/<time>, or a .ckpt file)"
    )
