"""Where each metric lives in a run's TensorBoard folder, and reading its curves back.

The layout (written by `rotlearn.lit.TensorBoardRunLogger`): `<run>/tensorboard/<run name>/`
holds one sub-run per stage, `train/`, `val/` and `test/`, so one card draws a run's training
and validation curves and its test value together. A metric logged as `<stage>/<name>` is drawn
in its stage's sub-run under a tag the stages share (`tensorboard_place`):

==========================  =========  ==========================
logged as                   sub-run    tag
==========================  =========  ==========================
`<stage>/err_<stat>`        stage      `error/<stat>` (mean, median, p10, p90; degrees)
`train/loss`, `val/loss`    stage      `learning/loss`
`train/lr`                  train      `learning/lr`
`time/epoch_s`              train      `learning/epoch_time_s`
`test/<name>` (others)      test       `test/<name>`
`ood/<name>`                test       `ood/<name>`
==========================  =========  ==========================

The step is the number of epochs trained. The HPARAMS session is in the `test/` sub-run.
"""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path

import numpy as np

__all__ = [
    "ERROR_STATS",
    "EVENTS_DIR",
    "SESSION_RUN",
    "STAGES",
    "event_runs",
    "read_curve",
    "tensorboard_place",
]

EVENTS_DIR = "tensorboard"  # below the run directory
STAGES = ("train", "val", "test")
SESSION_RUN = "test"  # the sub-run that holds the HPARAMS session
ERROR_STATS = ("mean", "median", "p10", "p90")
_RENAMED = {"time/epoch_s": ("train", "learning/epoch_time_s")}


def tensorboard_place(key: str) -> tuple[str, str]:
    """(sub-run, tag) of a metric logged as `key` (module docstring); ("", key) for a key of no
    stage (drawn in the run itself)."""
    if key in _RENAMED:
        return _RENAMED[key]
    stage, sep, name = key.partition("/")
    if stage == "ood" and sep:
        return SESSION_RUN, key
    if stage not in STAGES or not sep:
        return "", key
    if name.startswith("err_") and name[4:] in ERROR_STATS:
        return stage, f"error/{name[4:]}"
    return stage, f"test/{name}" if stage == "test" else f"learning/{name}"


def event_runs(run_dir: str | Path) -> list[Path]:
    """The TensorBoard runs of a run directory: `tensorboard/<name>/` folders (one; a run logged
    before the stages had sub-runs: `tensorboard/` itself)."""
    root = Path(run_dir) / EVENTS_DIR
    if not root.is_dir() or root.is_symlink():
        return []
    named = sorted(p for p in root.iterdir() if p.is_dir() and not p.is_symlink())
    return named or [root]


def read_curve(run_dir: str | Path, key: str) -> np.ndarray | None:
    """Per-epoch values of the metric `key` (e.g. "val/err_mean") from a run's TensorBoard
    events, in step order (one value per epoch; a step logged twice, as a resumed run may, keeps
    its last value); None when the run has no such series."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from rotlearn.logs import logger_at_least

    run, tag = tensorboard_place(key)
    for folder in event_runs(run_dir):
        for where, name in ((folder / run, tag), (folder, key)):  # the layout, then a flat one
            if not where.is_dir():
                continue
            with logger_at_least("tensorboard", logging.ERROR), contextlib.suppress(Exception):
                events = EventAccumulator(str(where), size_guidance={"scalars": 0}).Reload()
                if name in events.Tags().get("scalars", []):
                    by_step = {e.step: e.value for e in events.Scalars(name)}
                    return np.array([by_step[s] for s in sorted(by_step)], dtype=float)
    return None
