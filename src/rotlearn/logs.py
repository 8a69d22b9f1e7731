"""Console helpers shared by the training glue and the CLI: loggers and progress bars."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterable, Iterator
from typing import Any

__all__ = ["logger_at_least", "progress"]


@contextlib.contextmanager
def logger_at_least(name: str, level: int = logging.WARNING) -> Iterator[None]:
    """Raise the logger `name` to at least `level` meanwhile (e.g. Lightning's INFO lines that
    the run's own trainer has already printed, TensorBoard's event-reader chatter); restored
    on exit."""
    logger = logging.getLogger(name)
    previous = logger.level
    logger.setLevel(max(previous, level))
    try:
        yield
    finally:
        logger.setLevel(previous)


def progress(batches: Iterable[Any], what: str, trainer: Any = None) -> Iterable[Any]:
    """`batches` with a progress bar on stderr (`what`: its label) that shows only when they take
    over 2 s, and not at all where `trainer`'s own progress bar is off
    (`trainer.enable_progress_bar=false`: a log file gets no bars)."""
    if trainer is not None and getattr(trainer, "progress_bar_callback", None) is None:
        return batches
    from tqdm.auto import tqdm

    return tqdm(batches, desc=what, unit="batch", delay=2.0, leave=False, dynamic_ncols=True)
