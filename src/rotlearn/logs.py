"""Logging helpers shared by the training glue and the CLI (standard library only)."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

__all__ = ["logger_at_least"]


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
