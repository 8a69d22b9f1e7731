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
import os
from pathlib import Path

import numpy as np

from rotlearn.io import MAX_BYTES, UnreadableFileError, folder_entries

__all__ = [
    "ERROR_STATS",
    "EVENTS_DIR",
    "SESSION_RUN",
    "STAGES",
    "event_runs",
    "read_curve",
    "tensorboard_place",
]

log = logging.getLogger("rotlearn")
EVENTS_DIR = "tensorboard"  # below the run directory
STAGES = ("train", "val", "test")
SESSION_RUN = "test"  # the sub-run that holds the HPARAMS session
ERROR_STATS = ("mean", "median", "p10", "p90")
_RENAMED = {"time/epoch_s": ("train", "learning/epoch_time_s")}
# Files below a run's tensorboard/ folder that a report reads: each attempt writes one per
# stage, so a run resumed dozens of times stays well below. TensorBoard's reader lists a folder
# again for every file in it: 4,000 empty files (0 bytes) took 79 s to read.
MAX_EVENT_FILES = 256
MAX_EVENT_DEPTH = 8  # folder levels below tensorboard/ (<name>/<stage>: 2)


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


def _readable_events(run_dir: Path) -> bool:
    """Whether TensorBoard may read the run's event files: regular files inside the run, at most
    `MAX_EVENT_FILES` of them and `MAX_BYTES["TensorBoard events"]` in all (TensorBoard reads
    them unbounded; a named pipe would hang it). A warning names what is refused."""
    root = run_dir / EVENTS_DIR
    if not root.is_dir():
        return True  # nothing to read
    total, count, real_run = 0, 0, Path(os.path.realpath(run_dir))
    try:
        entries = list(folder_entries(root, 2 * MAX_EVENT_FILES, MAX_EVENT_DEPTH))
    except UnreadableFileError as exc:
        log.warning("%s; its events are not read", exc)
        return False
    for entry in entries:
        path = Path(entry.path)
        if entry.is_dir(follow_symlinks=False):
            continue
        if not (entry.is_file() and Path(os.path.realpath(path)).is_relative_to(real_run)):
            log.warning("%s: not a regular file inside the run; its events are not read", path)
            return False
        if (count := count + 1) > MAX_EVENT_FILES:
            log.warning("%s: over %d files; its events are not read", root, MAX_EVENT_FILES)
            return False
        total += entry.stat().st_size  # the entry's cached stat (links followed, as checked)
    if total > MAX_BYTES["TensorBoard events"]:
        log.warning("%s: over %d bytes of events; not read", root, MAX_BYTES["TensorBoard events"])
        return False
    return True


def read_curve(run_dir: str | Path, key: str) -> np.ndarray | None:
    """Per-epoch values of the metric `key` (e.g. "val/err_mean") from a run's TensorBoard
    events, in step order (one value per epoch; a step logged twice, as a resumed run may, keeps
    its last value); None when the run has no such series."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from rotlearn.logs import logger_at_least

    run, tag = tensorboard_place(key)
    if not _readable_events(Path(run_dir)):
        return None
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
