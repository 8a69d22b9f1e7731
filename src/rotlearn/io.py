"""File I/O: crash-safe writing (a reader sees the old file or the whole new one, never a part),
reading rows of numbers with errors that name the file and line, and the checks every dataset
reader shares: finite values, plain names and paths that stay inside their root.

Every file rotlearn writes itself (records, tables, figures, caches, the auto-encoder's weights)
goes through `atomic_write`, the one write-temporary-then-rename: it is created with the mode the
umask allows (0644 under umask 022, like a file `open` creates), so a colleague in a shared
folder can read the results."""

from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from rotlearn.errors import ConfigValueError

__all__ = [
    "atomic_write",
    "cache_file",
    "parse_number_rows",
    "plain_name",
    "read_json",
    "read_number_rows",
    "read_text_lines",
    "require_finite",
    "resolve_inside",
    "strict_int",
    "write_json_atomic",
    "write_text_atomic",
]

_INT = re.compile(r"[+-]?[0-9]+")


def read_json(path: str | os.PathLike) -> Any:
    """The JSON data of a record file (metrics.json, status.json, ...), or None where it is
    missing, unreadable or not JSON (a run killed mid-write, a damaged or foreign file)."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):  # ValueError: JSON or UTF-8 decoding
        return None


def _new_temporary(path: Path) -> Path:
    """A new empty file beside `path` (hidden, same suffix, so writers that add one, such as
    `numpy.save`, keep its name), created with mode 0666 minus the umask."""
    flags = os.O_CREAT | os.O_EXCL | os.O_WRONLY | getattr(os, "O_CLOEXEC", 0)
    while True:
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp{path.suffix}")
        try:
            os.close(os.open(tmp, flags, 0o666))
        except FileExistsError:
            continue
        return tmp


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike) -> Iterator[Path]:
    """Write `path` whole or not at all: yields the path of a new, empty temporary file beside
    `path` for any writer to fill (text, `numpy.save`, `torch.save`, a figure, a memmap); when
    the block ends, the file is synced to disk and renamed over `path`. If the block raises,
    the temporary file is removed and `path` is left as it was.

    The file gets the mode the umask allows (0644 under umask 022), as `open` gives a new file.

    Example::

        with atomic_write(run_dir / "table.npy") as tmp:
            np.save(tmp, table)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _new_temporary(path)
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """`text` (UTF-8) into `path`, atomically (`atomic_write`)."""
    with atomic_write(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_json_atomic(path: str | os.PathLike, data: Any) -> Path:
    """`write_text_atomic` of `data` as indented JSON."""
    return write_text_atomic(path, json.dumps(data, indent=2, sort_keys=True) + "\n")


# ---- numbers ------------------------------------------------------------------------------------


def require_finite(values: np.ndarray, lines: np.ndarray, where: str, layout: str) -> np.ndarray:
    """`values` unchanged if every entry is finite.

    Args:
        values: (N, ...) numbers read from a file, one row per line.
        lines: (N,) the 1-based line of each row.
        where: the file, for messages.
        layout: what a row holds, for messages.

    Raises:
        ValueError: "<where>:<line>: ..." naming the first row with a NaN or an infinity (also
            numbers too large for float64, such as 1e999) and how many rows have one.
    """
    bad = np.flatnonzero(~np.isfinite(values.reshape(len(values), -1)).all(axis=1))
    if len(bad):
        row = values[bad[0]].ravel().tolist()
        raise ValueError(
            f"{where}:{int(lines[bad[0]])}: not finite ({layout}): {row} "
            f"(NaN, inf, or beyond the range of {values.dtype}); {len(bad)} such row(s) in all"
        )
    return values


def strict_int(text: str, where: str) -> int:
    """`text` as an integer: optional sign and ASCII digits only (no "1.5", "1e9", "1_000").

    Raises:
        ValueError: "<where>: not an integer: ...".
    """
    if not _INT.fullmatch(text):
        raise ValueError(f"{where}: not an integer: {text!r}")
    return int(text)


def parse_number_rows(
    rows: Iterable[tuple[int, list[str]]], where: str, width: int, layout: str,
    extra_ok: bool = False, dtype: np.dtype | type = np.float64,
) -> np.ndarray:  # fmt: skip
    """Rows of number words -> (N, width) `dtype`, every number checked finite in `dtype` (a
    number beyond float32 is refused when reading float32).

    Args:
        rows: (line number, words) per row.
        where: the file, for messages.
        width: numbers per row; layout: what a row holds, for messages.
        extra_ok: keep the first `width` numbers of longer rows instead of refusing them.
        dtype: the floating dtype returned.

    Raises:
        ValueError: "<where>:<line>: ..." for the first row of the wrong length, with a word that
            is not a number, or with a NaN / infinity; "<where>: no rows" when there is none.
    """
    values, lines = [], []
    for lineno, words in rows:
        if len(words) < width or (len(words) > width and not extra_ok):
            raise ValueError(
                f"{where}:{lineno}: expected {width} numbers ({layout}), got {len(words)}"
            )
        try:
            values.append([float(w) for w in words[:width]])
        except ValueError:
            raise ValueError(f"{where}:{lineno}: not a number in {' '.join(words)!r}") from None
        lines.append(lineno)
    if not values:
        raise ValueError(f"{where}: no rows of numbers ({layout})")
    with np.errstate(over="ignore"):
        array = np.asarray(values, dtype=dtype)
    return require_finite(array, np.asarray(lines), where, layout)


def read_number_rows(
    path: str | os.PathLike, width: int, layout: str, extra_ok: bool = False, commas: bool = False,
    dtype: np.dtype | type = np.float64,
) -> np.ndarray:  # fmt: skip
    """The rows of a text file of numbers, (N, width) `dtype`, all finite: one row per non-blank
    line, `#` starting a comment.

    Args:
        path: the file.
        width: numbers per row.
        layout: what a row holds, for messages (e.g. "x y z").
        extra_ok: keep the first `width` numbers of longer rows instead of refusing them.
        commas: commas separate numbers too.
        dtype: the floating dtype returned (float64; float32 for point clouds).

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file and line of the first malformed row (wrong count, not a
            number, NaN or infinite), or an empty file or one that is not UTF-8 text.
    """
    path = Path(path)
    rows = []
    for lineno, line in enumerate(read_text_lines(path), start=1):
        text = line.split("#", 1)[0]
        words = (text.replace(",", " ") if commas else text).split()
        if words:
            rows.append((lineno, words))
    return parse_number_rows(rows, str(path), width, layout, extra_ok, dtype)


def read_text_lines(path: Path) -> list[str]:
    """The lines of a UTF-8 text file.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file (and the line) when it is not UTF-8 text.
    """
    if not path.is_file():
        raise FileNotFoundError(f"no input file at {path}")
    data = path.read_bytes()
    try:
        return data.decode("utf-8").splitlines()
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise ValueError(f"{path}:{line}: not UTF-8 text (byte {exc.start})") from None


# ---- names and paths ----------------------------------------------------------------------------


def _name_problem(name: str) -> str | None:
    """Why `name` is not one plain file or folder name, or None."""
    if name in ("", ".", ".."):
        return "empty, '.' or '..'"
    if any(c in name for c in "/\\\0"):
        return "it holds a path separator or NUL"
    return None


def plain_name(name: object, where: str | None = None, key: str | None = None) -> str:
    """`name` as a string, if it is one plain file or folder name: not empty, '.' or '..', no
    '/', '\\' or NUL. A plain name joined to a folder stays in that folder (up to symlinks:
    `resolve_inside`).

    Args:
        name: the name, from a config or a dataset file.
        where: for a name read from a file, "<file>:<line>"; the error is a ValueError.
        key: for a name from the config, the key (relative to the component, e.g.
            "train_sequences"); the error is a `ConfigValueError` on that key.

    Raises:
        ValueError / ConfigValueError: naming `where` or `key`, the name and what is wrong.
    """
    text = str(name)
    problem = _name_problem(text)
    if problem is None:
        return text
    message = f"{text!r} is not a plain file or folder name ({problem}): it could leave the dataset"
    if key is not None:
        raise ConfigValueError(key, message)
    raise ValueError(f"{where}: {message}")


def resolve_inside(root: str | os.PathLike, path: str | os.PathLike, where: str) -> Path:
    """`path` resolved (symlinks followed), if it lies inside `root` resolved.

    Args:
        root: the folder `path` must not leave (the dataset root, a cache folder).
        path: the path to check; it need not exist yet.
        where: what named `path` (a config key, "<file>:<line>"), for messages.

    Raises:
        ValueError: "<where>: <path> resolves to <target>, outside <root>".
    """
    real_root = Path(root).resolve()
    real = Path(path).resolve()
    if not real.is_relative_to(real_root):
        raise ValueError(f"{where}: {path} resolves to {real}, outside {real_root}")
    return real


def cache_file(
    cache_dir: str | os.PathLike, stem: str, where: str, root: str | os.PathLike | None = None
) -> Path:
    """`cache_dir / stem`, the stem of a cache built from dataset names (sequence, synset):
    checked to be a plain name whose `.npy` and `.json` resolve inside `cache_dir`, and inside
    `root` too when `cache_dir` lies in it (the default `<root>/.rotlearn_cache`: a dataset that
    ships that folder as a symlink cannot send the cache elsewhere).

    Raises:
        ValueError: naming `where` (the config keys the stem is built from).
    """
    path = Path(cache_dir) / plain_name(stem, where)
    within = [cache_dir]
    if root is not None and Path(os.path.abspath(cache_dir)).is_relative_to(os.path.abspath(root)):
        within.append(root)
    for folder in within:
        for suffix in (".npy", ".json"):
            resolve_inside(folder, path.with_suffix(suffix), where)
    return path
