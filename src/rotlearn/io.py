"""File I/O: crash-safe writing (a reader sees the old file or the whole new one, never a part)
and reading rows of numbers with errors that name the file and line."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["read_number_rows", "write_json_atomic", "write_text_atomic"]


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write `text` to a temporary file beside `path`, fsync it, then rename it over `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_json_atomic(path: str | os.PathLike, data: Any) -> Path:
    """`write_text_atomic` of `data` as indented JSON."""
    return write_text_atomic(path, json.dumps(data, indent=2, sort_keys=True) + "\n")


def read_number_rows(
    path: str | os.PathLike, width: int, layout: str, extra_ok: bool = False, commas: bool = False
) -> np.ndarray:
    """The rows of a text file of numbers, (N, width) float64: one row per non-blank line, `#`
    starting a comment.

    Args:
        path: the file.
        width: numbers per row.
        layout: what a row holds, for messages (e.g. "x y z").
        extra_ok: keep the first `width` numbers of longer rows instead of refusing them.
        commas: commas separate numbers too.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file and line of the first malformed row, or an empty file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no input file at {path}")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        text = line.split("#", 1)[0]
        words = (text.replace(",", " ") if commas else text).split()
        if not words:
            continue
        if len(words) < width or (len(words) > width and not extra_ok):
            raise ValueError(
                f"{path}:{lineno}: expected {width} numbers ({layout}), got {len(words)}"
            )
        try:
            rows.append([float(w) for w in words[:width]])
        except ValueError:
            raise ValueError(f"{path}:{lineno}: not a number in {line.strip()!r}") from None
    if not rows:
        raise ValueError(f"{path}: no rows of numbers ({layout})")
    return np.asarray(rows, dtype=np.float64)
