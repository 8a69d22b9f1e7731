"""File I/O at the run directory's boundary: bounded reads (a regular file only, a size cap per
kind of file, YAML without aliases, JSON and YAML with a depth limit), durable writes (a reader
sees the old file or the whole new one, never a part, also after a crash or a full disk), reading
rows of numbers with errors that name the file and line, and the checks every dataset reader
shares: finite values, plain names and paths that stay inside their root.

Every file rotlearn writes itself (records, tables, figures, caches, checkpoints) goes through
`atomic_write`, the one write-temporary-then-rename: the temporary file is created beside the
target with the mode the umask allows (0644 under umask 022, like a file `open` creates), so a
colleague in a shared folder can read the results; it is fsynced, renamed, and its folder fsynced;
a failed write (a full disk, a quota) is a `WriteError` naming the file and the cause, and leaves
the previous file as it was."""

from __future__ import annotations

import array as pyarray
import contextlib
import errno
import glob
import json
import logging
import math
import os
import pickletools
import re
import secrets
import stat
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

try:
    import fcntl
except ImportError:  # Windows: no advisory locks (a killed write's temporary file stays)
    fcntl = None

from rotlearn.errors import ConfigError

__all__ = [
    "MAX_BYTES",
    "MAX_DEPTH",
    "MAX_NODES",
    "OPAQUE",
    "UnreadableFileError",
    "WriteError",
    "atomic_write",
    "cache_file",
    "cache_manifest",
    "folder_entries",
    "numbered_lines",
    "parse_number_rows",
    "parse_yaml",
    "plain_name",
    "plain_names",
    "plain_pickle",
    "read_bytes",
    "read_cached_array",
    "read_json",
    "read_manifest",
    "read_number_array",
    "read_number_rows",
    "read_record",
    "read_table",
    "read_text",
    "read_text_file",
    "read_yaml",
    "remove_stale_temporaries",
    "require_finite",
    "resolve_inside",
    "rewrite_in_place",
    "strict_int",
    "sync_folder",
    "text_lines",
    "tree_problem",
    "word_rows",
    "write_bytes_atomic",
    "write_json_atomic",
    "write_text_atomic",
]

log = logging.getLogger("rotlearn")

_INT = re.compile(r"[+-]?[0-9]+")
# Cc, Zl, Zp, Cs, and the format characters that reorder or hide text (bidi controls, zero-width
# space, word joiner, BOM): not ZWNJ and ZWJ (U+200C, U+200D), which Persian and Indic names use
_UNPRINTABLE = re.compile(
    "[\x00-\x1f\x7f-\x9f\u2028\u2029\ud800-\udfff\u061c\u200b\u200e\u200f\u202a-\u202e"
    "\u2060-\u2064\u2066-\u2069\ufeff]"
)
_LINE_BREAK = re.compile(r"\r\n|[\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029]")  # str.splitlines
_KIB, _MIB, _GIB = 2**10, 2**20, 2**30

# The most bytes rotlearn reads from one file of each kind: what a genuine file needs, with room.
# A larger file is refused unread (a file that grows past it while being read, too).
MAX_BYTES: dict[str, int] = {
    "JSON record": 16 * _MIB,  # status.json, metrics.json, timing.json, jobs.json, test_errors.json
    "YAML config": 4 * _MIB,  # .hydra/config.yaml and hydra.yaml
    "overrides file": 256 * _KIB,  # .hydra/overrides.yaml: one run's command line
    "CSV table": 256 * _MIB,  # ood.csv, ood_samples.csv
    "metrics log": 64 * _MIB,  # csv/metrics.csv (a row per logging step; a run's is kilobytes)
    "text file": 256 * _MIB,  # a dataset's text files (poses, frame lists, point clouds)
    "number array": 256 * _MIB,  # a .npy array of numbers (rotlearn-predict's point pairs)
    "camera frame": _GIB,  # an image file: twice a frame of 2^26 pixels (the pixel budget,
    # rotlearn.data.image_header.MAX_PIXELS) as uncompressed 16-bit RGBA
    "checkpoint": 4 * _GIB,  # a .ckpt on disk, and its records once decompressed
    "calibration record": 4 * _KIB,  # checkpoints/temperature.json, ood_thresholds.json
    "TensorBoard events": 256 * _MIB,  # a run's tensorboard/ folder, all event files together
}
MAX_LINE_CHARS = _MIB  # a line of a text file of rows (`word_rows`): split into words, ~24x
MAX_DEPTH = 64  # nesting of a JSON or YAML document (rotlearn's own files nest a few levels)
MAX_NODES = 2**20  # values in one loaded document or checkpoint (a tensor counts as one)
MAX_YAML_NODES = 2**16  # values in one YAML document (a run's config holds a few hundred): a
# 4 MiB config of 2 million list items took eval 5 minutes and 2.7 GB to merge and a report more


class UnreadableFileError(ValueError):
    """A file that rotlearn refuses to read: not a regular file (a FIFO, a device, a folder),
    larger than its kind's cap, outside the folder it must stay in, or not well-formed data of
    its kind (nested too deeply, a YAML alias). The message names the file."""


class WriteError(OSError):
    """A durable write failed (a full disk, a quota, permissions): the message names the file
    and the cause; the file that was there before is unchanged."""

    def __init__(self, code: int | None, message: str) -> None:
        super().__init__(code, message)
        self.message = message

    def __str__(self) -> str:
        return self.message


# ---- bounded reads ------------------------------------------------------------------------------


def _what(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a named pipe (FIFO)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):  # fmt: skip
        if test(mode):
            return name
    return "not a regular file"


def read_bytes(path: str | os.PathLike, kind: str, root: str | os.PathLike | None = None) -> bytes:
    """The bytes of a regular file, at most `MAX_BYTES[kind]` of them.

    The file is opened without blocking (a named pipe is refused at once, never waited on) and
    read in chunks up to the cap, so neither a FIFO, a device such as /dev/zero, nor an endless
    or huge file can hang the reader or fill its memory.

    Args:
        path: the file.
        kind: a key of `MAX_BYTES` ("JSON record", "YAML config", ...), for the cap and messages.
        root: if given, `path` resolved (symlinks and `..` followed) must lie inside it.

    Raises:
        FileNotFoundError: no such file (the message names it).
        UnreadableFileError: not a regular file, larger than the cap, or outside `root`.
        OSError: it cannot be read (permissions, I/O error).
    """
    path = Path(path)
    cap = MAX_BYTES[kind]
    if root is not None:
        real, real_root = Path(os.path.realpath(path)), Path(os.path.realpath(root))
        if not real.is_relative_to(real_root):
            raise UnreadableFileError(
                f"{path}: resolves to {real}, outside {real_root}; refusing to read it"
            )
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: no such file") from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise UnreadableFileError(f"{path}: {_what(mode)}, not a regular file; not read")
        chunks, total = [], 0
        while chunk := os.read(fd, min(_MIB, cap + 1 - total)):
            chunks.append(chunk)
            total += len(chunk)
            if total > cap:
                raise UnreadableFileError(
                    f"{path}: too large for a {kind} (over {cap} bytes); not read"
                )
        return b"".join(chunks)
    finally:
        os.close(fd)


def read_text(path: str | os.PathLike, kind: str, root: str | os.PathLike | None = None) -> str:
    """`read_bytes` decoded as UTF-8.

    Raises:
        as `read_bytes`; UnreadableFileError naming the file and line where it is not UTF-8.
    """
    data = read_bytes(path, kind, root)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise _not_utf8(path, data, exc) from None


def _not_utf8(path: str | os.PathLike, data: bytes, exc: UnicodeDecodeError) -> UnreadableFileError:
    """The error naming the file and the line of `data` (the whole file) where UTF-8 fails."""
    line = data[: exc.start].count(b"\n") + 1
    return UnreadableFileError(f"{path}:{line}: not UTF-8 text (byte {exc.start})")


def tree_problem(tree: Any) -> str | None:
    """Why loaded data (dicts, lists and tuples of leaves) is unsafe to walk: nested deeper than
    `MAX_DEPTH`, or more than `MAX_NODES` values once its shared references are followed (a
    pickle's memo lets a file of a kilobyte hold a tree of 2**40 values); None where it is safe.
    Without recursion; stops at the first bound passed."""
    stack, count = [(tree, 1)], 0
    while stack:
        node, depth = stack.pop()
        if (count := count + 1) > MAX_NODES:
            return f"more than {MAX_NODES} values (shared references followed)"
        if isinstance(node, dict | list | tuple):
            if depth > MAX_DEPTH:
                return f"nested too deeply (over {MAX_DEPTH} levels)"
            children = node.values() if isinstance(node, dict) else node
            stack.extend((child, depth + 1) for child in children)
    return None


def folder_entries(
    root: str | os.PathLike, max_entries: int, max_depth: int
) -> Iterator[os.DirEntry]:
    """Every entry below folder `root`, folders before what they hold, in name order within a
    folder; symlinks are yielded, never followed. Without recursion (Python 3.11's `os.walk`
    and `rglob` recurse: 1100 nested folders end them in a RecursionError).

    Raises:
        UnreadableFileError: naming `root` past `max_entries` entries, the folder past
            `max_depth` levels, or a folder that cannot be read.
    """
    count, folders = 0, [(os.fspath(root), 0)]
    while folders:
        folder, depth = folders.pop()
        if depth > max_depth:
            raise UnreadableFileError(f"{folder}: folders nested more than {max_depth} deep")
        try:
            with os.scandir(folder) as found:
                entries = sorted(found, key=lambda e: e.name)
        except OSError as exc:
            raise UnreadableFileError(f"{folder}: cannot be read ({exc.strerror})") from None
        for entry in entries:
            if (count := count + 1) > max_entries:
                raise UnreadableFileError(f"{root}: more than {max_entries} files and folders")
            yield entry
            if entry.is_dir(follow_symlinks=False):
                folders.append((entry.path, depth + 1))


# pickle opcodes whose argument is the value they push (strings, bytes, numbers)
_PICKLED_VALUES = {"INT", "BININT", "BININT1", "BININT2", "LONG", "LONG1", "LONG4", "FLOAT",
                   "BINFLOAT", "UNICODE", "BINUNICODE", "SHORT_BINUNICODE", "BINUNICODE8",
                   "BINBYTES", "SHORT_BINBYTES", "BINBYTES8", "STRING", "BINSTRING",
                   "SHORT_BINSTRING"}  # fmt: skip
_PICKLED_CONSTANTS = {"NONE": None, "NEWTRUE": True, "NEWFALSE": False}
_OPCODES_PER_VALUE = 5  # a value takes at most a push, a memo put, a mark and an append


class _Opaque:
    """What a pickle would build by calling code (`plain_pickle`): not read."""

    def __repr__(self) -> str:
        return "<not plain data>"


OPAQUE = _Opaque()


class _Pairs(list):
    """A dict as `plain_pickle` reads it: its (key, value) pairs, no key hashed yet."""


class _Call(list):
    """What unpickling would build by calling code (a global, a reduce, a persistent id, a set):
    everything given to it, kept so that `tree_problem` counts what the call would hash."""


def plain_pickle(data: bytes) -> Any:
    """What a pickle holds, read opcode by opcode (`pickletools.genops`) where it is plain data:
    dicts, lists, tuples, strings, bytes, numbers, booleans, None. Nothing is imported, built,
    called or hashed while reading: a value that unpickling would make by calling code (a tensor,
    an OrderedDict, a set, any global) reads as `OPAQUE`. Before a key is hashed, everything it
    builds (keys, what each call would be given, what it throws away) must pass `tree_problem`
    (shared references followed), so a pickle that would make an unpickler hash or walk without
    end (a key of 2**40 values in 200 bytes) is refused; shared references come out as copies.

    Reading stops after a few opcodes per value of that bound, so a large file of opcodes that
    build nothing (marks, memo puts) is refused in seconds, not read for minutes.

    Raises:
        ValueError: not a whole pickle, one whose stack does not add up, one past
            `tree_problem`'s bounds or its opcode budget, or a key that cannot be one (a list).
    """
    stack: list[Any] = []
    marks: list[int] = []
    memo: dict[int, Any] = {}
    dropped: list[Any] = []  # built and thrown away: an unpickler hashed its keys all the same

    def since_mark() -> list[Any]:
        items = stack[marks.pop() :]
        del stack[len(stack) - len(items) :]
        return items

    def popped(count: int) -> list[Any]:
        if (start := len(stack) - count) < 0:
            raise IndexError("stack underflow")
        items = stack[start:]
        del stack[start:]
        return items

    try:
        for count, (op, arg, _) in enumerate(pickletools.genops(data)):
            if count > _OPCODES_PER_VALUE * MAX_NODES:  # what passes needs fewer: stop reading
                raise ValueError(f"more than {_OPCODES_PER_VALUE * MAX_NODES} opcodes")
            name = op.name
            if name in _PICKLED_VALUES:
                stack.append(arg)
            elif name in _PICKLED_CONSTANTS:
                stack.append(_PICKLED_CONSTANTS[name])
            elif name in ("EMPTY_DICT", "EMPTY_LIST", "EMPTY_TUPLE"):
                stack.append({"EMPTY_DICT": _Pairs(), "EMPTY_LIST": [], "EMPTY_TUPLE": ()}[name])
            elif name == "MARK":
                marks.append(len(stack))
            elif name in ("TUPLE", "LIST"):
                stack.append(tuple(since_mark()) if name == "TUPLE" else since_mark())
            elif name == "DICT":
                items = since_mark()
                stack.append(_Pairs(zip(items[::2], items[1::2], strict=True)))
            elif name in ("TUPLE1", "TUPLE2", "TUPLE3"):
                stack.append(tuple(popped(int(name[-1]))))
            elif name in ("APPEND", "APPENDS", "SETITEM", "SETITEMS"):
                items = since_mark() if name.endswith("S") else popped(2 if "SET" in name else 1)
                target, setting = stack[-1], name.startswith("SETITEM")
                if setting:
                    items = list(zip(items[::2], items[1::2], strict=True))
                wanted = _Pairs if setting else list
                if not isinstance(target, _Call) and type(target) is not wanted:
                    raise ValueError(f"{name} into a {type(target).__name__}")
                target.extend(items)  # a call's (an OrderedDict's) are counted, not kept
            elif name in ("PUT", "BINPUT", "LONG_BINPUT", "MEMOIZE"):
                memo[len(memo) if name == "MEMOIZE" else arg] = stack[-1]
            elif name in ("GET", "BINGET", "LONG_BINGET"):
                stack.append(memo[arg])
            elif name == "POP":
                dropped.append(stack.pop())
            elif name == "POP_MARK":
                dropped.extend(since_mark())
            elif name == "DUP":
                stack.append(stack[-1])
            elif name == "STOP":  # the last opcode genops yields (it raises where there is none)
                break
            elif name not in ("PROTO", "FRAME"):  # what calls code: a _Call of what it is given
                before = op.stack_before
                given = []
                if pickletools.markobject in before:
                    given = since_mark()
                    before = before[: before.index(pickletools.markobject)]
                given = [*popped(len(before)), *given]
                stack.extend([_Call(given) for _ in op.stack_after])
        found = stack.pop()
    except (IndexError, KeyError, ValueError) as exc:
        raise ValueError(f"not a pickle of plain data ({exc})") from None
    if problem := tree_problem([found, stack, dropped]):  # everything it builds
        raise ValueError(problem)

    def plain(value: Any) -> Any:  # at most MAX_DEPTH deep and MAX_NODES values (tree_problem)
        if isinstance(value, _Call):
            return OPAQUE
        if isinstance(value, _Pairs):
            return {plain(key): plain(item) for key, item in value}
        if isinstance(value, list | tuple):
            return type(value)(map(plain, value))
        return value

    try:
        return plain(found)
    except TypeError as exc:  # a list as a key
        raise ValueError(f"not a pickle of plain data ({exc})") from None


def read_record(
    path: str | os.PathLike, root: str | os.PathLike | None = None, kind: str = "JSON record"
) -> Any:
    """The JSON data of a record file (status.json, metrics.json, ...), read bounded
    (`read_bytes`). NaN and the infinities are accepted (metrics may be NaN).

    Raises:
        FileNotFoundError: no such file.
        UnreadableFileError: not a regular file, too large, outside `root`, not UTF-8, not JSON,
            or nested deeper than `MAX_DEPTH`; the message names the file.
    """
    text = read_text(path, kind, root)
    try:
        data = json.loads(text)
    except RecursionError:
        problem = f"nested too deeply (over {MAX_DEPTH} levels)"
    except ValueError as exc:
        raise UnreadableFileError(f"{path}: not JSON ({exc})") from None
    else:
        problem = tree_problem(data)
    if problem:
        raise UnreadableFileError(f"{path}: JSON {problem}")
    return data


def read_json(
    path: str | os.PathLike, root: str | os.PathLike | None = None, kind: str = "JSON record"
) -> Any:
    """`read_record`, or None where the file is missing or refused (a run killed before it wrote
    the file, a damaged or foreign one): for readers that go on without it. A refused file is
    logged as a warning naming it and why."""
    try:
        return read_record(path, root, kind)
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        log.warning("%s (ignored)", exc)
        return None


def read_manifest(path: str | os.PathLike) -> Any:
    """A dataset cache's `.json` manifest (`read_record`, bounded), or None where it is missing
    or cannot be read (a named pipe, too large, not JSON): the cache is then rebuilt."""
    try:
        return read_record(path)
    except (OSError, ValueError):
        return None


def read_cached_array(
    path: str | os.PathLike, dtype: Any, shape: tuple[int | None, ...]
) -> np.ndarray | None:
    """A dataset cache's `.npy` array, memory-mapped read-only (never unpickled), if it is a
    regular file holding `dtype` of `shape` (None: any length on that axis); None otherwise (a
    foreign, damaged or hostile cache: it is rebuilt)."""
    if not Path(path).is_file():
        return None
    try:
        array = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError):
        return None
    if not isinstance(array, np.ndarray):  # an .npz archive (np.load's NpzFile)
        array.close()
        return None
    fits = array.dtype == np.dtype(dtype) and array.ndim == len(shape)
    if not fits or any(n is not None and n != m for n, m in zip(shape, array.shape, strict=True)):
        return None
    return array


def read_table(
    path: str | os.PathLike,
    root: str | os.PathLike | None = None,
    kind: str = "CSV table",
    columns: Sequence[str] | None = None,
) -> Any:
    """A UTF-8 CSV file as a pandas DataFrame, read bounded (`read_bytes`, `kind`), parsed from
    the bytes read (no copy as text).

    Args:
        columns: only these columns, those the file has (None: every column).

    Raises:
        FileNotFoundError, UnreadableFileError: as `read_bytes`; UnreadableFileError naming the
            file when it is not UTF-8 or pandas cannot parse it.
    """
    import io

    import pandas as pd

    data = read_bytes(path, kind, root)
    wanted = None if columns is None else set(columns).__contains__
    try:
        return pd.read_csv(io.BytesIO(data), encoding="utf-8", usecols=wanted)
    except UnicodeDecodeError as exc:  # its position is pandas' buffer's, not the file's
        try:
            data.decode("utf-8")
        except UnicodeDecodeError as whole:
            raise _not_utf8(path, data, whole) from None
        raise UnreadableFileError(f"{path}: not a CSV table ({exc})") from None
    except (ValueError, pd.errors.ParserError) as exc:
        raise UnreadableFileError(f"{path}: not a CSV table ({exc})") from None


def parse_yaml(text: str, where: str) -> Any:
    """Plain data of a YAML document: no tags beyond YAML's own (safe loading), no aliases (a
    file rotlearn writes has none; an alias can multiply a small file into gigabytes), nesting
    at most `MAX_DEPTH`, at most `MAX_YAML_NODES` values (scalars and collections).

    Raises:
        UnreadableFileError: naming `where` (and the line) when it is not such YAML.
    """
    import yaml

    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    depth = nodes = 0
    try:
        for event in yaml.parse(text, Loader=loader):
            if isinstance(event, yaml.NodeEvent) and (nodes := nodes + 1) > MAX_YAML_NODES:
                raise UnreadableFileError(f"{where}: more than {MAX_YAML_NODES} YAML values")
            if isinstance(event, yaml.AliasEvent):
                line = event.start_mark.line + 1 if event.start_mark else "?"
                raise UnreadableFileError(
                    f"{where}:{line}: YAML alias *{event.anchor}: aliases are refused in files "
                    "rotlearn reads"
                )
            if isinstance(event, yaml.CollectionStartEvent):
                depth += 1
                if depth > MAX_DEPTH:
                    raise UnreadableFileError(
                        f"{where}: YAML nested too deeply (over {MAX_DEPTH} levels)"
                    )
            elif isinstance(event, yaml.CollectionEndEvent):
                depth -= 1
        return yaml.load(text, Loader=loader)
    except yaml.YAMLError as exc:
        first = str(exc).strip().splitlines()
        raise UnreadableFileError(f"{where}: not plain YAML data ({' '.join(first)})") from None


def read_yaml(
    path: str | os.PathLike, kind: str = "YAML config", root: str | os.PathLike | None = None
) -> Any:
    """`parse_yaml` of a file read bounded (`read_text`).

    Raises:
        FileNotFoundError: no such file.
        UnreadableFileError: as `read_bytes` and `parse_yaml`, naming the file.
    """
    return parse_yaml(read_text(path, kind, root), str(path))


# ---- durable writes -----------------------------------------------------------------------------


def sync_folder(folder: Path) -> None:
    """Make the renames in `folder` durable (where the platform can: not on Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return  # Windows: folders cannot be opened; the rename is as durable as it gets
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):
            raise
    finally:
        os.close(fd)


def _temporary_name(path: Path, tag: str, kind: str = "tmp", escape=str) -> str:
    """The name of a temporary file for `path` (hidden, same suffix, so writers that add one,
    such as `numpy.save`, keep its name); `tag`: 8 hex digits, or (with `escape=glob.escape`)
    a glob pattern of them; `kind`: "tmp", or "new" while it is made (`_new_temporary`)."""
    return f"{escape(f'.{path.name}.')}{tag}{escape(f'.{kind}{path.suffix}')}"


def _new_temporary(path: Path) -> tuple[Path, int]:
    """A new empty file beside `path`, created with mode 0666 minus the umask, never through a
    symlink (`O_EXCL`), and an open descriptor holding an exclusive `flock` on it, which marks
    it in use until the writer closes it or dies (`remove_stale_temporaries`). It is made and
    locked under another name, then linked to its own, so it never bears that name unlocked."""
    flags = os.O_CREAT | os.O_EXCL | os.O_WRONLY | getattr(os, "O_CLOEXEC", 0)
    while True:
        tag = secrets.token_hex(4)
        made, tmp = (path.with_name(_temporary_name(path, tag, k)) for k in ("new", "tmp"))
        try:
            fd = os.open(made, flags, 0o666)
        except FileExistsError:
            continue
        try:
            if fcntl is not None:
                with contextlib.suppress(OSError):  # no locks there: never removed as stale
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            try:
                os.link(made, tmp)  # never over another writer's (EEXIST)
            except FileExistsError:
                tmp = None  # that name is taken: another tag
            except OSError:  # a filesystem without hard links
                os.rename(made, tmp)
                return tmp, fd
            os.unlink(made)
        except BaseException:
            os.close(fd)
            with contextlib.suppress(OSError):
                os.unlink(made)
            raise
        if tmp is not None:
            return tmp, fd
        os.close(fd)


def remove_stale_temporaries(path: str | os.PathLike) -> None:
    """Remove the temporary files of `atomic_write(path)` that no writer holds: left by a write
    that was killed (SIGKILL, the out-of-memory killer, a power cut), e.g. a frame cache of
    gigabytes. A live writer's, in this process or another, holds its `flock`; a symlink, a
    FIFO or a folder of that name is left alone (a received run's folder may hold one). Where
    locks are not what `flock` gives (NFS: emulated with fcntl locks, which a file opened for
    reading cannot take exclusively) or there are none (Windows), nothing is removed."""
    path = Path(path)
    if fcntl is None:
        return
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    for tmp in path.parent.glob(_temporary_name(path, "[0-9a-f]" * 8, escape=glob.escape)):
        try:
            if not stat.S_ISREG(tmp.lstat().st_mode):  # not opened: a device's open acts
                continue
            fd = os.open(tmp, flags)
        except OSError:  # gone, or not ours to read
            continue
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):  # swapped since the lstat
                continue
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            tmp.unlink(missing_ok=True)
            log.info("removed %s, left by a write that was killed", tmp)
        except OSError:  # held: a write in progress (or a filesystem without locks)
            pass
        finally:
            os.close(fd)


def _write_error(path: Path, exc: OSError) -> WriteError:
    kept = "; the previous file is unchanged" if os.path.lexists(path) else ""
    return WriteError(exc.errno, f"cannot write {path}: {exc.strerror or exc}{kept}")


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike) -> Iterator[Path]:
    """Write `path` whole or not at all, durably: yields the path of a new, empty temporary file
    beside `path` for any writer to fill (text, `numpy.save`, a figure, a memmap); when the block
    ends, the file is synced to disk, renamed over `path` (a symlink there is replaced, never
    written through) and the folder synced. If the block raises, the temporary file is removed
    and `path` is left as it was; one left by a writer that was killed is removed by
    `remove_stale_temporaries(path)` (the frame caches call it before they are built again).

    The file gets the mode the umask allows (0644 under umask 022), as `open` gives a new file.

    Example::

        with atomic_write(run_dir / "table.npy") as tmp:
            np.save(tmp, table)

    Raises:
        WriteError: an OSError while creating, filling, syncing or renaming the file (a full
            disk, a quota, permissions), naming `path` and the cause; `path` is unchanged.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp, held = _new_temporary(path)
    except (FileExistsError, NotADirectoryError) as exc:  # a file where a folder goes
        folders = (path.parent, *path.parent.parents)
        file = next((f for f in folders if f.exists() and not f.is_dir()), path.parent)
        message = f"cannot write {path}: {file} is a file, not a folder"
        raise WriteError(exc.errno, message) from None
    except OSError as exc:
        raise _write_error(path, exc) from None
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
        sync_folder(path.parent)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, OSError) and not isinstance(exc, WriteError):
            raise _write_error(path, exc) from None
        raise
    finally:
        os.close(held)


def write_bytes_atomic(path: str | os.PathLike, data: bytes | bytearray | memoryview) -> Path:
    """`data` into `path`, durably (`atomic_write`).

    Raises:
        WriteError: as `atomic_write`.
    """
    with atomic_write(path) as tmp:
        fd = os.open(tmp, os.O_WRONLY | getattr(os, "O_BINARY", 0))
        try:
            view = memoryview(data).cast("B")
            while view:
                view = view[os.write(fd, view[: 64 * _MIB]) :]
        finally:
            os.close(fd)
    return Path(path)


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """`text` (UTF-8) into `path`, atomically (`atomic_write`)."""
    with atomic_write(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_json_atomic(path: str | os.PathLike, data: Any) -> Path:
    """`write_text_atomic` of `data` as indented JSON."""
    return write_text_atomic(path, json.dumps(data, indent=2, sort_keys=True) + "\n")


def rewrite_in_place(path: str | os.PathLike, data: bytes) -> Path:
    """Overwrite an existing regular file's bytes in place, then cut it to `data`'s length: the
    fallback for a small record that must change on a full disk (a status that says FAILED),
    where `write_bytes_atomic` cannot create its temporary file. The file's own blocks are
    reused, so no new space is needed while `data` is not longer than what the file holds (a
    record of a few hundred bytes in one block). Not atomic: a crash midway can leave a mix.

    Raises:
        WriteError: naming `path` and the cause (also when it is not an existing regular file).
    """
    path = Path(path)
    flags = os.O_WRONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags | getattr(os, "O_BINARY", 0))
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise OSError(errno.EINVAL, "not a regular file")
            view = memoryview(data).cast("B")
            os.lseek(fd, 0, os.SEEK_SET)
            rest = view
            while rest:
                rest = rest[os.write(fd, rest) :]
            os.ftruncate(fd, len(view))
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:
        raise WriteError(exc.errno, f"cannot write {path}: {exc.strerror or exc}") from None
    return path


# ---- numbers ------------------------------------------------------------------------------------


def require_finite(
    values: np.ndarray, lines: np.ndarray, where: str, layout: str, bound: float | None = None
) -> np.ndarray:
    """`values` unchanged if every entry is finite (and at most `bound` in magnitude).

    Args:
        values: (N, ...) numbers read from a file, one row per line.
        lines: (N,) the 1-based line of each row.
        where: the file, for messages.
        layout: what a row holds, for messages.
        bound: the largest magnitude allowed (None: any finite number).

    Raises:
        ValueError: "<where>:<line>: ..." naming the first row with a NaN or an infinity (also
            numbers too large for float64, such as 1e999) or a number beyond `bound`, and how
            many rows have one.
    """
    rows = values.reshape(len(values), -1)
    good = np.isfinite(rows) if bound is None else np.abs(rows) <= bound  # NaN: not <= bound
    bad = np.flatnonzero(~good.all(axis=1))
    if len(bad):
        row = values[bad[0]].ravel().tolist()
        beyond = f"beyond the range of {values.dtype}" if bound is None else f"beyond +-{bound:g}"
        raise ValueError(
            f"{where}:{int(lines[bad[0]])}: not finite ({layout}): {row} "
            f"(NaN, inf, or {beyond}); {len(bad)} such row(s) in all"
        )
    return values


def strict_int(text: str, where: str) -> int:
    """`text` as an integer: optional sign and ASCII digits only (no "1.5", "1e9", "1_000").

    Raises:
        ValueError: "<where>: not an integer: ...", also for more digits than Python converts
            (`sys.get_int_max_str_digits`, 4300), whose own error names no file.
    """
    if not _INT.fullmatch(text):
        raise ValueError(f"{where}: not an integer: {text!r}")
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"{where}: not an integer: {len(text)} digits, too many") from None


def parse_number_rows(
    rows: Iterable[tuple[int, list[str]]], where: str, width: int, layout: str,
    extra_ok: bool = False, dtype: np.dtype | type = np.float64, bound: float | None = None,
    max_rows: int | None = None,
) -> np.ndarray:  # fmt: skip
    """Rows of number words -> (N, width) `dtype`, every number checked finite in `dtype` (a
    number beyond float32 is refused when reading float32).

    Args:
        rows: (line number, words) per row.
        where: the file, for messages.
        width: numbers per row; layout: what a row holds, for messages.
        extra_ok: keep the first `width` numbers of longer rows instead of refusing them.
        dtype: the floating dtype returned.
        bound: every number's magnitude at most this (None: finite is enough).
        max_rows: at most this many rows (None: any number); reading stops at the one past it.

    Raises:
        ValueError: "<where>:<line>: ..." for the first row of the wrong length, with a word that
            is not a number, with a NaN / infinity or a number beyond `bound`, or past
            `max_rows`; "<where>: no rows" when there is none.
    """
    values, lines = pyarray.array("d"), pyarray.array("q")  # 8 bytes a number, not a float object
    for lineno, words in rows:
        if len(words) < width or (len(words) > width and not extra_ok):
            raise ValueError(
                f"{where}:{lineno}: expected {width} numbers ({layout}), got {len(words)}"
            )
        try:
            values.extend([float(w) for w in words[:width]])
        except ValueError:
            raise ValueError(f"{where}:{lineno}: not a number in {' '.join(words)!r}") from None
        lines.append(lineno)
        if max_rows is not None and len(lines) > max_rows:
            raise ValueError(f"{where}:{lineno}: more than {max_rows} rows ({layout})")
    if not lines:
        raise ValueError(f"{where}: no rows of numbers ({layout})")
    with np.errstate(over="ignore"):
        numbers = np.frombuffer(values, np.float64).reshape(-1, width).astype(dtype, copy=False)
    return require_finite(numbers, np.frombuffer(lines, np.int64), where, layout, bound)


def read_number_rows(
    path: str | os.PathLike, width: int, layout: str, extra_ok: bool = False, commas: bool = False,
    dtype: np.dtype | type = np.float64, bound: float | None = None, max_rows: int | None = None,
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
        bound, max_rows: as `parse_number_rows`.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file and line of the first malformed row (wrong count, not a
            number, NaN or infinite, beyond `bound`, past `max_rows`, longer than
            `MAX_LINE_CHARS`), or an empty file or one that is not UTF-8 text.
    """
    rows = word_rows(read_text_file(path), str(path), commas)
    return parse_number_rows(rows, str(path), width, layout, extra_ok, dtype, bound, max_rows)


def word_rows(text: str, where: str, commas: bool = False) -> Iterator[tuple[int, list[str]]]:
    """(line number, words) of each line of `text` that has words before its `#` comment (with
    `commas`, commas separate words too), one at a time (`text_lines`): a row's words are
    dropped once the caller has parsed them.

    Raises:
        ValueError: "<where>:<line>: ..." for a line longer than `MAX_LINE_CHARS`
            (`numbered_lines`).
    """
    for lineno, line in numbered_lines(text, where):
        kept = line.split("#", 1)[0]
        if words := (kept.replace(",", " ") if commas else kept).split():
            yield lineno, words


def numbered_lines(text: str, where: str) -> Iterator[tuple[int, str]]:
    """(line number, line) of each line of `text` (`text_lines`), for a reader that splits them.

    Raises:
        ValueError: "<where>:<line>: ..." for a line longer than `MAX_LINE_CHARS` (split into
            words or fields, it would take about 24 times its size).
    """
    for lineno, line in enumerate(text_lines(text), start=1):
        if len(line) > MAX_LINE_CHARS:
            raise ValueError(f"{where}:{lineno}: a line of {len(line)} characters, over the "
                             f"{MAX_LINE_CHARS} a line of rows may have")  # fmt: skip
        yield lineno, line


def text_lines(text: str, block: int = _MIB) -> Iterator[str]:
    """`text.splitlines()`, a block of about `block` characters at a time (each cut after a line
    break, any that `splitlines` breaks at, so every line is whole): a file of short lines is
    not held as one string each."""
    start = 0
    while start < len(text):
        cut = _LINE_BREAK.search(text, start + block)
        end = len(text) if cut is None else cut.end()
        yield from text[start:end].splitlines()
        start = end


def read_number_array(path: str | os.PathLike, width: int, layout: str) -> np.ndarray:
    """A `.npy` file of rows of `width` real numbers, (N, width) or (B, N, width) float64, all
    finite. Read bounded (`read_bytes`, "number array": the file, and the float64 array it
    becomes, which is up to 8 times larger) and parsed from numpy's header, whose shape and
    dtype are checked against the bytes that follow before anything is allocated; never
    unpickled.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file: not a regular file or too large, not one `.npy` array (a
            `.npz` archive, a pickle, a header that does not match its data), Python objects,
            numbers that are not real (complex, bool, text), another shape, or the index of the
            first row with a NaN or an infinity.
    """
    import io

    from numpy.lib import format as npy

    _require_input(path)
    data = read_bytes(path, "number array")
    stream = io.BytesIO(data)
    if data.startswith(b"PK"):
        raise UnreadableFileError(f"{path}: a .npz archive, not one .npy array (numpy.save one)")
    try:
        version = npy.read_magic(stream)
        header = {(1, 0): npy.read_array_header_1_0, (2, 0): npy.read_array_header_2_0}[version]
        shape, fortran, dtype = header(stream)
    except (ValueError, KeyError, EOFError) as exc:
        why = f"version {exc}" if isinstance(exc, KeyError) else str(exc).splitlines()[0]
        raise UnreadableFileError(f"{path}: not a .npy array ({why})") from None
    if dtype.hasobject:
        raise UnreadableFileError(f"{path}: holds Python objects, which rotlearn never unpickles")
    if dtype.kind not in "iuf" or dtype.names is not None:
        raise ValueError(f"{path}: holds {dtype} values, not real numbers ({layout})")
    body, size = memoryview(data)[stream.tell() :], math.prod(shape) * dtype.itemsize  # exact
    if len(body) != size:
        raise UnreadableFileError(
            f"{path}: its header says {shape} {dtype} ({size} bytes) but {len(body)} bytes follow"
        )
    if len(shape) not in (2, 3) or shape[-1] != width:
        expected = f"(N, {width}) or (B, N, {width})"
        raise ValueError(f"{path}: expected an array of shape {expected}, got {shape}")
    if (wide := math.prod(shape) * 8) > (cap := MAX_BYTES["number array"]):  # int8: 8 x the file
        raise UnreadableFileError(
            f"{path}: its {shape} numbers take {wide} bytes as float64, over the {cap} bytes a "
            "number array may take; not read"
        )
    array = np.frombuffer(body, dtype).reshape(shape, order="F" if fortran else "C")
    values = array.astype(np.float64)
    rows = ~np.isfinite(values).all(axis=-1)
    if rows.any():
        at = tuple(int(i) for i in np.argwhere(rows)[0])
        raise ValueError(
            f"{path}: row {list(at)} is not finite ({layout}): {values[at].tolist()}; "
            f"{int(rows.sum())} such row(s) in all"
        )
    return values


def read_text_file(path: str | os.PathLike) -> str:
    """A UTF-8 text file of a dataset's, read bounded (`read_text`, "text file").

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file (and the line) when it is not UTF-8 text, not a regular
            file or too large.
    """
    _require_input(path)
    return read_text(path, "text file")


def _require_input(path: str | os.PathLike) -> None:
    """FileNotFoundError naming an input file that is not there (a dangling symlink is there:
    `read_bytes` refuses it, saying why)."""
    if not os.path.lexists(path):
        raise FileNotFoundError(f"no input file at {path}")


# ---- names and paths ----------------------------------------------------------------------------


def _name_problem(name: str) -> str | None:
    """Why `name` is not one plain file or folder name ("(what): why it matters"), or None."""
    if name in ("", ".", ".."):
        return "(empty, '.' or '..'): it could leave the dataset"
    if any(c in name for c in "/\\\0"):
        return "(it holds a path separator or NUL): it could leave the dataset"
    if _UNPRINTABLE.search(name):
        return (
            "(a line break, a control character, a bidi override or an invisible character, or "
            "bytes that are not UTF-8): a message naming it would be garbled"
        )
    return None


def plain_name(name: object, where: str | None = None, key: str | None = None) -> str:
    """`name` as a string, if it is one plain file or folder name: not empty, '.' or '..', no
    '/', '\\' or NUL, no control character, bidi control or invisible character (a zero-width
    space), line break or undecodable byte. A plain name joined to a folder stays in that
    folder (up to symlinks: `resolve_inside`).

    Args:
        name: the name, from a config or a dataset file.
        where: for a name read from a file, "<file>:<line>"; the error is a ValueError.
        key: for a name from the config, the key (relative to the component, e.g.
            "train_sequences"); the error is a `ConfigError` on that key.

    Raises:
        ValueError / ConfigError: naming `where` or `key`, the name and what is wrong.
    """
    text = str(name)
    problem = _name_problem(text)
    if problem is None:
        return text
    message = f"{text!r} is not a plain file or folder name {problem}"
    if key is not None:
        raise ConfigError(key, message)
    raise ValueError(f"{where}: {message}")


def plain_names(names: Iterable[object], key: str) -> list[str]:
    """`plain_name` of each entry of the config list `key` (sequences, scenes), each once.

    Raises:
        ConfigError: on `key`, naming the entry that is not a plain name or is listed twice
            (its pairs would be read and counted twice).
    """
    found = [plain_name(name, key=key) for name in names]
    for i, name in enumerate(found):
        if name in found[:i]:
            raise ConfigError(key, f"lists {name!r} twice ({list(names)!r}); each once")
    return found


def resolve_inside(root: str | os.PathLike, path: str | os.PathLike, where: str) -> Path:
    """`path` resolved (symlinks followed), if it lies inside `root` resolved.

    Args:
        root: the folder `path` must not leave (the dataset root, a cache folder).
        path: the path to check; it need not exist yet.
        where: what named `path` (a config key, "<file>:<line>"), for messages.

    Raises:
        ValueError: "<where>: <path> resolves to <target>, outside <root>", or a symlink loop
            (Python 3.11's `resolve` raises RuntimeError for one, 3.13's OSError).
    """
    try:
        real_root, real = Path(root).resolve(), Path(path).resolve()
    except (RuntimeError, OSError) as exc:
        raise ValueError(f"{where}: {path} cannot be resolved ({exc}): a symlink loop") from None
    if not real.is_relative_to(real_root):
        raise ValueError(f"{where}: {path} resolves to {real}, outside {real_root}")
    return real


def cache_manifest(files: Sequence[Path], recipe: dict, what: str = "file") -> dict:
    """What a cache built from `files` records of them, so that it is rebuilt when any changes:
    the recipe, and each file's path, size, modification time and inode change time (ns), and
    the file it is (its inode: a symlinked frame pointed at another file of the same size and
    times kept the cache; not its device, which an NFS mount numbers differently on each host).
    The change time is set by the file system when a file is written, unpacked, copied or
    renamed, and no archive carries it: a cache shipped with a dataset (its manifest matching
    the paths, sizes and modification times, which an archive keeps, beside frames other than
    the files') is never trusted over the files; it is rebuilt from them.

    Raises:
        FileNotFoundError: "<file>: <what> <i>: no such file", for the first missing one.
    """
    stats = []
    for i, path in enumerate(files):
        try:
            stats.append(path.stat())
        except FileNotFoundError:
            raise FileNotFoundError(f"{path}: {what} {i}: no such file") from None
    return {
        "recipe": recipe,
        "files": [str(f) for f in files],
        "sizes": [s.st_size for s in stats],
        "mtimes_ns": [s.st_mtime_ns for s in stats],
        "ctimes_ns": [s.st_ctime_ns for s in stats],
        "inodes": [s.st_ino for s in stats],  # not the device: a mount's number differs by host
    }


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
