"""Reading checkpoints and run directories safely: the one loader every rebuild goes through.

A checkpoint is read with `torch.load(weights_only=True)` (tensors and plain data, never pickled
code), and the run config it carries is checked against rotlearn's allowlist of buildable
components (`rotlearn.trust`) before anything is built from it. `rotlearn.load`, `rotlearn-predict`,
`rotlearn-eval` and the OOD evaluation's auto-encoder all load through `load_run`. What the file
holds is bounded (depth, values with shared references followed, and weights no larger than their
storage) before anything walks it. `saved_config` reads only the run config, without torch (the
pickle parsed as data), for a command's first look before torch loads.

The OOD evaluation's calibrated threshold lives beside the checkpoints, in
`<run>/checkpoints/ood_thresholds.json` ({"score": str, "threshold": number, "q": number,
"reference": "val" or "train", the set whose scores gave it; older files lack it);
`load_run` reads it (strictly: it is data from a run directory, not trusted) when present.

The belief's post-hoc calibration (`calibrate`, `rotlearn.lit.calibration`) lives there too, in
`<run>/checkpoints/temperature.json` ({"temperature": number > 0, "checkpoint": the file name
of the checkpoint it was fitted for, "val_nll", "val_nll_uncalibrated": number or null,
"num_val": int, and optionally "credible_masses": the recalibration of the credible levels, K + 1
numbers rising from 0 to 1, `rotlearn.bingham.LevelMap`}); `load_run` reads it as strictly and
applies it (`SavedRun.temperature`, `SavedRun.level_map`) only to the checkpoint it names.
"""

from __future__ import annotations

import itertools
import logging
import math
import os
import pickle
import stat
import struct
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import numpy as np

from rotlearn.extras import require
from rotlearn.io import (
    MAX_BYTES,
    plain_name,
    plain_pickle,
    read_bytes,
    read_json,
    write_bytes_atomic,
)
from rotlearn.paths import checkpoint_file
from rotlearn.trust import UntrustedConfigError, trusted_config

if TYPE_CHECKING:  # torch is imported where it is used: a first look at a file needs none
    from torch import Tensor

__all__ = [
    "TEMPERATURE_FILE",
    "THRESHOLDS_FILE",
    "SavedRun",
    "UnsafeCheckpointError",
    "UntrustedConfigError",
    "check_weights",
    "checkpoint_temperature",
    "load_checkpoint",
    "load_run",
    "read_temperature",
    "read_thresholds",
    "rebuildable",
    "resolve_checkpoint",
    "save_checkpoint",
    "saved_config",
    "temperature_range",
    "tested_checkpoint",
]

THRESHOLDS_FILE = "ood_thresholds.json"  # beside the checkpoints it calibrates
TEMPERATURE_FILE = "temperature.json"  # beside the checkpoint whose belief it tempers
# A checkpoint's records decompress to at most this many times the file's size: torch writes them
# uncompressed (ratio 1); a deflated bomb (a few MB that inflate to gigabytes) is refused unread.
_MAX_INFLATION = 4
_FLOAT32_MAX = float(np.finfo(np.float32).max)  # beliefs and OOD scores are float32

log = logging.getLogger("rotlearn")


class UnsafeCheckpointError(pickle.UnpicklingError, ValueError):
    """The file is not a checkpoint of tensors and plain data; it was not unpickled."""


def resolve_checkpoint(path: str | os.PathLike) -> Path:
    """A checkpoint file, or a run directory (meaning its checkpoints/last.ckpt): see
    `rotlearn.paths.checkpoint_file`.

    Raises:
        FileNotFoundError: no checkpoint there, saying what `path` is instead (a sweep
            directory, naming its jobs, or a folder that holds no run).
        UnsafeCheckpointError: a run directory whose last.ckpt is a symlink out of the run.
    """
    path = Path(path)
    if path.is_dir():
        _inside_run(path, path / "checkpoints" / "last.ckpt")
    return checkpoint_file(path)


def _inside_run(run: Path, file: Path) -> None:
    real = Path(os.path.realpath(file))
    if os.path.lexists(file) and not real.is_relative_to(os.path.realpath(run)):
        raise UnsafeCheckpointError(f"{file}: a symlink to {real}, outside the run; not read")


def tested_checkpoint(path: str | os.PathLike) -> Path:
    """The checkpoint `load_run` reads for `path`: a file as it is; for a run directory, the
    weights its test scored, the file in its checkpoints/ that its metrics.json names
    (`tested_checkpoint`: best.ckpt for a run trained with `test_ckpt=best`; runs recorded before
    the name was: best.ckpt where `tested_weights` is best), else last.ckpt (a run not tested yet,
    whose training a resume would continue). So its temperature and OOD threshold, fitted when it
    was tested, belong to the weights loaded.

    Raises:
        FileNotFoundError, UnsafeCheckpointError: as `resolve_checkpoint`, also for the named
            file (a symlink out of the run).
    """
    last = resolve_checkpoint(path)
    run = Path(path)
    if not run.is_dir():
        return last
    metrics = read_json(run / "metrics.json", root=run)
    metrics = metrics if isinstance(metrics, dict) else {}
    name = metrics.get("tested_checkpoint")
    if name is None and metrics.get("tested_weights") == "best":
        name = "best.ckpt"  # the best checkpoint's name in conf/callbacks/default.yaml
    if name is None or name == last.name:
        return last
    try:  # a plain file name (no folder, not . or ..): it stays in checkpoints/
        tested = run / "checkpoints" / plain_name(name, where=str(run / "metrics.json"))
    except ValueError:
        tested = None
    if tested is None or not tested.is_file():
        log.warning(
            "%s: the tested checkpoint %r is not a file in %s; %s is read instead",
            run / "metrics.json", name, run / "checkpoints", last.name,
        )  # fmt: skip
        return last
    _inside_run(run, tested)
    return tested


def save_checkpoint(checkpoint: dict[str, Any], path: str | os.PathLike) -> Path:
    """Write a checkpoint (tensors and plain data) durably: serialised in memory, then written
    to a temporary file beside `path`, fsynced and renamed over it
    (`rotlearn.io.write_bytes_atomic`).

    Raises:
        WriteError: naming `path` and the cause (a full disk, a quota); the checkpoint that was
            at `path` is unchanged and loadable.
    """
    import io

    import torch

    buffer = io.BytesIO()
    torch.save(checkpoint, buffer)
    return write_bytes_atomic(path, buffer.getbuffer())


def _one_reading(
    path: Path, handle: Any, size: int, members: list[zipfile.ZipInfo]
) -> zipfile.ZipInfo | None:
    """The `<folder>/data.pkl` record (<folder>: the first record's) that torch's reader (miniz)
    reads in the open zip archive `handle` of `size` bytes, listed by zipfile as `members`; None
    if there is none. Refused where the two readers could read different bytes: end records not
    at the file's end (miniz reads the central directory at the offset they give, zipfile where
    it ends before them; miniz finds the zip64 record where the locator says, zipfile just before
    it), another count of records, or record names not unique as miniz compares them (bytes,
    ASCII case ignored: torch reads the first of two, zipfile the last) or holding a NUL (zipfile
    cuts a name there).

    Raises:
        UnsafeCheckpointError: naming the file and which of these it is.
    """
    handle.seek(max(size - 98, 0))  # [zip64 record (56), zip64 locator (20),] end record (22)
    tail = handle.read(98)
    end, locator, record64 = tail[-22:], tail[-42:-22], tail[-98:-42]
    if len(end) < 22 or end[:4] != b"PK\x05\x06" or end[20:] != b"\0\0":
        raise UnsafeCheckpointError(
            f"{path}: its zip end record is not at its end (a comment or data after it); not read"
        )
    count, directory, offset = struct.unpack("<H2I", end[10:20])
    start = size - 22
    if locator[:4] == b"PK\x06\x07":  # zip64: both readers take its record's values
        if record64[:4] != b"PK\x06\x06" or struct.unpack("<Q", locator[8:16])[0] != size - 98:
            raise UnsafeCheckpointError(
                f"{path}: its zip64 locator does not point at the zip64 end record before it"
            )
        count, directory, offset = struct.unpack("<3Q", record64[32:56])
        start = size - 98
    if offset + directory != start or count != len(members):
        raise UnsafeCheckpointError(
            f"{path}: its zip central directory is not the {count} records that end where its "
            "end record begins (data before or between them): zip readers would differ on what "
            "it holds; not read"
        )
    raw = [m.orig_filename.encode("utf-8" if m.flag_bits & 0x800 else "cp437") for m in members]
    keys = [name.lower() for name in raw]  # miniz ignores ASCII case
    seen: set[bytes] = set()
    for member, name, key in zip(members, raw, keys, strict=True):
        if b"\0" in name:
            raise UnsafeCheckpointError(
                f"{path}: its zip record named {member.orig_filename!r} holds a NUL (zipfile reads "
                "the name up to it, torch whole); not read"
            )
        if key in seen:
            raise UnsafeCheckpointError(
                f"{path}: two of its zip records are named {member.filename!r} (case ignored: "
                "torch reads the first, zipfile the last); not read"
            )
        seen.add(key)
    wanted = (raw[0].split(b"/")[0] + b"/data.pkl").lower() if raw else None
    return next((m for m, key in zip(members, keys, strict=True) if key == wanted), None)


@contextmanager
def _opened(path: Path) -> Iterator[tuple[BinaryIO, int]]:
    """Checkpoint file `path` opened once for every read of it (its check and torch's load: a
    file swapped in between is not read), with its size: refused unless it is a regular file
    of at most `MAX_BYTES["checkpoint"]` bytes.

    Raises:
        UnsafeCheckpointError: naming the file and which of these it is.
    """
    cap = MAX_BYTES["checkpoint"]
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    with os.fdopen(fd, "rb") as handle:
        info = os.fstat(handle.fileno())
        if not stat.S_ISREG(info.st_mode):
            raise UnsafeCheckpointError(f"{path} is not a regular file; not read")
        if info.st_size > cap:
            raise UnsafeCheckpointError(f"{path} is larger than a checkpoint may be ({cap} bytes)")
        yield handle, info.st_size


def _plain_checkpoint(path: Path, handle: BinaryIO, size: int) -> Any:
    """What the checkpoint file `path`, open as `handle` (`_opened`) with `size` bytes, holds,
    read as data without torch (`rotlearn.io.plain_pickle`: tensors and other objects as
    OPAQUE) from the pickle torch would read, `<folder>/data.pkl` where <folder> is the first
    record's. Before that, refuse a file that is not a whole zip archive (a truncated file has
    no central directory; a damaged record fails its CRC), or whose records would decompress
    beyond `MAX_BYTES["checkpoint"]` or `_MAX_INFLATION` times the file's size, or that torch's
    reader (miniz) could read otherwise than Python's zipfile (`_one_reading`).

    Raises:
        UnsafeCheckpointError: naming the file and which of these it is, or a pickle that is not
            one or is past `plain_pickle`'s bounds.
    """
    try:
        archive = zipfile.ZipFile(handle)
        members = archive.infolist()
        inflated = sum(m.file_size for m in members)
        bounded = inflated <= min(MAX_BYTES["checkpoint"], _MAX_INFLATION * max(size, 1) + 2**20)
        record = _one_reading(path, handle, size, members)
        data = archive.read(record) if bounded and record is not None else b""
    except UnsafeCheckpointError:
        raise
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, struct.error) as exc:
        raise UnsafeCheckpointError(
            f"{path} is not a whole PyTorch checkpoint (a zip archive): truncated, damaged or "
            f"another kind of file ({exc})"
        ) from None
    if not bounded:
        raise UnsafeCheckpointError(
            f"{path}: its records would decompress to {inflated} bytes from a file of "
            f"{size}; refusing it unread (a PyTorch checkpoint is stored uncompressed)"
        )
    try:
        return plain_pickle(data)
    except ValueError as exc:
        raise UnsafeCheckpointError(f"{path} is not a checkpoint rotlearn reads: {exc}") from None


def load_checkpoint(path: str | os.PathLike, map_location: Any = "cpu") -> dict[str, Any]:
    """`torch.load(path, weights_only=True)`: refuses, without running it, any pickled payload.

    Args:
        path: a `.ckpt` file or a run directory.
        map_location: as in `torch.load`.

    Before torch reads it, the file must be a regular file of at most `MAX_BYTES["checkpoint"]`
    bytes and a whole zip archive whose records decompress to at most that many bytes (and at most
    a few times the file's size) and that torch's zip reader reads as zipfile does (unique
    record names, the central directory where its end records say), so a truncated, huge,
    decompression-bomb or two-faced file is refused at once, naming it; what it holds, read
    first as data (`rotlearn.io.plain_pickle`), must nest at most `MAX_DEPTH` levels and, its
    shared references followed and what each object would be built from included, hold at most
    `MAX_NODES` values, so that neither torch's unpickler (hashing a key) nor any walk of the
    result (a config check, Lightning's restore) can be made to take forever by a file of a few
    hundred bytes.

    Raises:
        FileNotFoundError: no such checkpoint.
        UnsafeCheckpointError: the file is not a dict of tensors and plain data: it carries
            objects that only a full unpickler could build (such a file can run code when
            loaded; rotlearn never loads it), or it is no checkpoint at all (truncated, too large,
            a decompression bomb).
    """
    import torch

    path = resolve_checkpoint(path)
    with _opened(path) as (handle, size):  # one handle: torch reads the bytes checked
        _plain_checkpoint(path, handle, size)  # bounded before torch's unpickler hashes a key
        handle.seek(0)
        try:
            checkpoint = torch.load(handle, map_location=map_location, weights_only=True)
        except pickle.UnpicklingError as exc:
            reason = next((line for line in str(exc).splitlines() if "GLOBAL" in line), "")
            detail = f" ({reason.strip()})" if reason else ""
            raise UnsafeCheckpointError(
                f"refusing to load {path}: it is not a checkpoint of tensors and plain data"
                f"{detail}. A file that needs a full unpickler can run code when loaded; rotlearn "
                "only reads checkpoints with torch.load(weights_only=True)."
            ) from None
        except Exception as exc:  # a damaged or foreign file fails in many ways (KeyError, ...)
            text = str(exc).strip()
            first = text.splitlines()[0] if text else ""
            if "weights_only" in first:  # never pass on torch's advice to unpickle
                first = ""
            raise UnsafeCheckpointError(
                f"{path} is not a readable PyTorch checkpoint ({type(exc).__name__}"
                + (f": {first}" if first else "")
                + ")"
            ) from None
    if not isinstance(checkpoint, dict):
        raise UnsafeCheckpointError(
            f"{path} is not a checkpoint: it holds a {type(checkpoint).__name__}, not a dict"
        )
    return checkpoint


def saved_config(path: Path) -> Any:
    """The run config (`rotlearn_config`) that checkpoint file `path` carries, read without torch
    and without unpickling anything (`rotlearn.io.plain_pickle`), within `load_checkpoint`'s
    bounds; None where it holds none. A first look, to refuse a run before torch loads;
    `load_run` is what reads a checkpoint.

    Raises:
        UnsafeCheckpointError: as `load_checkpoint`, naming the file.
    """
    with _opened(path) as (handle, size):
        checkpoint = _plain_checkpoint(path, handle, size)
    return checkpoint.get("rotlearn_config") if isinstance(checkpoint, dict) else None


@dataclass(frozen=True)
class SavedRun:
    """A trained run as read from its checkpoint, safe to rebuild.

    Attributes:
        path: the checkpoint file.
        config: the run's resolved config (a `DictConfig`): no interpolations, and every
            `_target_` on rotlearn's allowlist.
        state_dict: the LightningModule's weights, name -> tensor.
        ood: the calibrated OOD threshold written by the OOD evaluation beside the checkpoint
            (`THRESHOLDS_FILE`), {"score": str, "threshold": float, "q": float}, or None.
        temperature: the belief's post-hoc temperature T (A -> A / T) fitted for this
            checkpoint (`TEMPERATURE_FILE`); 1.0 without one, or when the file names another
            checkpoint.
        level_map: the recalibration of the tempered belief's credible levels fitted with it
            (a `rotlearn.bingham.LevelMap`), or None.
    """

    path: Path
    config: Any
    state_dict: dict[str, Tensor]
    ood: dict[str, Any] | None = field(default=None)
    temperature: float = 1.0
    level_map: Any = None

    @property
    def task(self) -> str:
        """ "rotation" or "autoencoder": the `task` of the saved model's class (`model._target_`,
        already on the allowlist), or the `task` key of configs saved before the model group."""
        from hydra.utils import get_class
        from omegaconf import OmegaConf

        target = OmegaConf.select(self.config, "model._target_")
        if target is None:
            return str(self.config.get("task", "rotation"))
        return str(getattr(get_class(target), "task", "unknown"))

    def _instantiate(self, key: str) -> Any:
        from hydra.errors import InstantiationException
        from hydra.utils import instantiate
        from omegaconf import OmegaConf

        node = OmegaConf.select(self.config, key)
        if node is None:
            raise ValueError(f"{self.path}: the saved config has no {key!r} node")
        try:
            return instantiate(node)
        except (InstantiationException, TypeError, ValueError) as exc:
            reason = str(exc).strip().splitlines()
            raise ValueError(
                f"{self.path}: the saved config's {key} cannot be built "
                f"({reason[-1] if reason else type(exc).__name__})"
            ) from None

    def check_fits(self, key: str, prefix: str | None = None) -> None:
        """Build the config node `key` on the meta device (no memory is allocated, whatever sizes
        the config names) and check that the stored weights under `prefix` (default: `key`;
        "": the whole state_dict) fit it exactly: the same names, shapes and kinds of dtype,
        floating weights finite (`check_weights`).

        Raises:
            ValueError: naming the checkpoint and what does not fit.
        """
        import torch

        with torch.device("meta"):
            module = self._instantiate(key)
        expected = module.state_dict() if isinstance(module, torch.nn.Module) else {}
        named = key if prefix is None else prefix
        check_weights(expected, self._stored(key, prefix), str(self.path), named)

    def build(self, key: str, prefix: str | None = None) -> Any:
        """Instantiate the config node `key` (e.g. "net", "rep"), after checking on the meta
        device that the stored weights under `prefix` (default: `key`) fit it (`check_fits`),
        and load them into it (a module without weights, such as a head, gets none).

        Raises:
            ValueError: naming the checkpoint: the node cannot be built, or the weights do not
                fit it (missing, unexpected, another shape, not floating point, not finite).
        """
        import torch

        self.check_fits(key, prefix)
        built = self._instantiate(key)
        if isinstance(built, torch.nn.Module):
            built.load_state_dict(self._stored(key, prefix), strict=True)
        return built

    def _stored(self, key: str, prefix: str | None) -> dict[str, Tensor]:
        if prefix == "":
            return self.state_dict
        return self.weights(key if prefix is None else prefix)

    def weights(self, prefix: str) -> dict[str, Tensor]:
        """The weights of the submodule `prefix` (e.g. "net"), with the prefix removed."""
        start = f"{prefix}."
        return {k[len(start) :]: v for k, v in self.state_dict.items() if k.startswith(start)}


def _listed(names: list[str], limit: int = 6) -> str:
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def check_weights(
    expected: dict[str, Tensor], stored: dict[str, Tensor], where: str, prefix: str = ""
) -> None:
    """Check stored weights against a module's state_dict (built on the meta device).

    Args:
        expected: name -> tensor of the module the weights are for (only shapes and dtypes
            are read).
        stored: name -> tensor read from a checkpoint.
        where: the checkpoint, for messages.
        prefix: the module's name in the checkpoint ("net"), prefixed to names in messages.

    Raises:
        ValueError: naming `where` and the first names at fault: missing or unexpected names,
            another shape, a floating tensor stored as integers or bools (or the reverse),
            a floating weight that is NaN or infinite in the module's dtype, a sparse weight or
            one without data (meta device), or weights that hold more bytes than they store (a
            file of kilobytes whose views of one value would make a model of gigabytes).
    """
    import torch

    full = (lambda name: f"{prefix}.{name}") if prefix else (lambda name: name)
    missing = sorted(map(full, set(expected) - set(stored)))
    unexpected = sorted(map(full, set(stored) - set(expected)))
    if missing or unexpected:
        parts = [f"missing {_listed(missing)}" if missing else "",
                 f"unexpected {_listed(unexpected)}" if unexpected else ""]  # fmt: skip
        raise ValueError(
            f"{where}: the stored weights do not fit the saved config's model "
            f"({'; '.join(p for p in parts if p)})"
        )
    odd = sorted(full(n) for n, t in stored.items() if t.layout != torch.strided or t.is_meta)
    if odd:  # a sparse tensor has no storage to measure; a meta one no data
        raise ValueError(
            f"{where}: weights must be dense tensors with data; sparse or on the meta device: "
            f"{_listed(odd)}"
        )
    storages = {s.data_ptr(): s.nbytes() for s in (t.untyped_storage() for t in stored.values())}
    held = sum(t.numel() * t.element_size() for t in stored.values())
    if held > sum(storages.values()):  # before anything is computed from or built for them
        raise ValueError(
            f"{where}: its weights hold {held} bytes but store {sum(storages.values())}: views "
            "that repeat stored values (a stride of 0, names sharing storage) are refused"
        )
    for name, want in expected.items():
        have = stored[name]
        if tuple(have.shape) != tuple(want.shape):
            raise ValueError(
                f"{where}: weight {full(name)} is stored with shape {tuple(have.shape)}, but the "
                f"saved config builds {tuple(want.shape)}"
            )
        if want.is_floating_point() != have.is_floating_point() or have.is_complex():
            kind = "floating point" if want.is_floating_point() else str(want.dtype)
            raise ValueError(
                f"{where}: weight {full(name)} is stored as {have.dtype}; it must be {kind}"
            )
        if want.is_floating_point() and not bool(torch.isfinite(have.to(want.dtype)).all()):
            raise ValueError(
                f"{where}: weight {full(name)} holds NaN or infinite values (in {want.dtype})"
            )


def _number(value: Any) -> bool:
    """A finite JSON number (not a bool; an integer too large for a float is not finite)."""
    if not isinstance(value, int | float) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def _read_record(path: Path, what: str) -> Any:
    """The JSON in `path` (a small record file, read bounded: `rotlearn.io.read_text`), refusing
    NaN and the infinities and nesting too deep to parse; ValueError naming the file otherwise."""
    import json

    data = read_bytes(path, "calibration record", root=path.parent)  # no symlink out of it

    def refuse(constant: str) -> None:
        raise ValueError(f"{constant} is not a number")

    try:
        return json.loads(data.decode("utf-8"), parse_constant=refuse)
    except ValueError as exc:
        raise ValueError(f"{path}: not a JSON {what} ({exc})") from None
    except RecursionError:
        raise ValueError(f"{path}: not a JSON {what} (nested too deeply)") from None


_OOD_KEYS = {"score", "threshold", "q", "reference"}


def _check_ood(ood: Any, path: Path, what: str) -> dict[str, Any]:
    """`ood` if it is exactly {score: str, threshold: finite number, q: number in [0, 1]}, and
    optionally reference: "val" or "train" (the set whose scores gave the threshold; files
    written before it was recorded have none)."""
    expected = '{score: str, threshold: number, q: number in [0, 1][, reference: "val" | "train"]}'
    if not isinstance(ood, dict) or not {"score", "threshold", "q"} <= set(ood) <= _OOD_KEYS:
        keys = sorted(map(str, ood)) if isinstance(ood, dict) else type(ood).__name__
        raise ValueError(f"{path}: {what} must be {expected}, got {keys}")
    if not isinstance(ood["score"], str) or not ood["score"]:
        raise ValueError(f"{path}: {what}'s score must be a name, got {ood['score']!r}")
    for key in ("threshold", "q"):
        if not _number(ood[key]):
            raise ValueError(f"{path}: {what}'s {key} must be a finite number, got {ood[key]!r}")
    if not 0.0 <= ood["q"] <= 1.0:
        raise ValueError(f"{path}: {what}'s q must lie in [0, 1], got {ood['q']!r}")
    largest = _FLOAT32_MAX  # scores are compared in float32
    if not -largest <= ood["threshold"] <= largest:
        raise ValueError(
            f"{path}: {what}'s threshold must lie within float32's range (|t| <= {largest:.3g}), "
            f"got {ood['threshold']!r}"
        )
    if ood.get("reference", "val") not in ("val", "train"):
        raise ValueError(
            f'{path}: {what}\'s reference must be "val" or "train", got {ood["reference"]!r}'
        )
    checked = {"score": ood["score"], "threshold": float(ood["threshold"]), "q": float(ood["q"])}
    return checked | ({"reference": ood["reference"]} if "reference" in ood else {})


def read_thresholds(path: str | os.PathLike) -> dict[str, Any] | None:
    """The calibrated OOD threshold in `path` (a `THRESHOLDS_FILE`), or None if there is none.

    Raises:
        ValueError: the file is not JSON of exactly {score: str, threshold: number, q: number in
            [0, 1]}, with an optional reference: "val" or "train" (the message names the file).
    """
    path = Path(path)
    if not os.path.lexists(path):
        return None
    ood = _read_record(path, "OOD threshold file")
    return _check_ood(ood, path, "the OOD threshold")


_TEMPERATURE_KEYS = {"temperature", "checkpoint", "val_nll", "val_nll_uncalibrated", "num_val"}
_OPTIONAL_TEMPERATURE_KEYS = {"credible_masses"}
_MAX_MASSES = 101  # knots of a level map (rotlearn.bingham.calibration.LEVEL_KNOTS + 1 = 21)


def temperature_range() -> tuple[float, float]:
    """The temperatures a record may hold: A / T and T * A stay finite in float32 for every
    belief the Bingham code supports (eigenvalue spread up to MAX_DISPERSION), so the tempered
    beliefs, their DT and their samples are finite numbers. A fit never leaves this range on
    float32 beliefs. (rotlearn.bingham is imported here, not with this module: the refusals that
    read a checkpoint should not wait for it.)"""
    from rotlearn.bingham import MAX_DISPERSION

    top = _FLOAT32_MAX
    return MAX_DISPERSION / top, top / MAX_DISPERSION


def read_temperature(path: str | os.PathLike) -> dict[str, Any] | None:
    """The post-hoc temperature record in `path` (a `TEMPERATURE_FILE`), or None if there is none.

    Returns:
        {"temperature": float > 0, "checkpoint": str (a file name), "val_nll": float,
        "val_nll_uncalibrated": float or None, "num_val": int >= 1, "credible_masses": list of
        floats or None}.

    Raises:
        ValueError: the file is larger than 4096 bytes, not JSON, holds NaN or an infinity, lacks
            or adds a key, or holds a temperature that is not a number in `temperature_range()`
            (about 3e-31 to 3e30), a checkpoint that is not a plain file name, a count that is
            not a positive integer, or credible masses that are not 2 to 101 numbers rising from
            0 to 1; the message names the file. Nothing is half-read: the record is checked whole
            before it is returned.
    """
    path = Path(path)
    if not os.path.lexists(path):
        return None
    record = _read_record(path, "temperature file")
    expected = (
        "{temperature: number > 0, checkpoint: file name, val_nll: number, "
        "val_nll_uncalibrated: number or null, num_val: int}"
    )
    if not isinstance(record, dict) or not (
        _TEMPERATURE_KEYS <= set(record) <= _TEMPERATURE_KEYS | _OPTIONAL_TEMPERATURE_KEYS
    ):
        keys = sorted(map(str, record)) if isinstance(record, dict) else type(record).__name__
        raise ValueError(f"{path}: the temperature record must be {expected}, got {keys}")
    t = record["temperature"]
    low, high = temperature_range()
    if not _number(t) or not low <= t <= high:
        raise ValueError(
            f"{path}: temperature must be a number in [{low:.3g}, {high:.3g}] (A / T must stay "
            f"finite in float32), got {t!r}"
        )
    name = record["checkpoint"]
    if not isinstance(name, str) or not name or Path(name).name != name or name in (".", ".."):
        raise ValueError(f"{path}: checkpoint must be a checkpoint's file name, got {name!r}")
    for key in ("val_nll", "val_nll_uncalibrated"):
        value = record[key]
        if not _number(value) and not (key == "val_nll_uncalibrated" and value is None):
            raise ValueError(f"{path}: {key} must be a finite number, got {value!r}")
    count = record["num_val"]
    if not isinstance(count, int) or isinstance(count, bool) or count < 1:
        raise ValueError(f"{path}: num_val must be a positive integer, got {count!r}")
    masses = record.get("credible_masses")
    if masses is not None:
        ok = (
            isinstance(masses, list) and 2 <= len(masses) <= _MAX_MASSES
            and all(_number(m) for m in masses) and masses[0] == 0 and masses[-1] == 1
            and all(b >= a for a, b in itertools.pairwise(masses))
        )  # fmt: skip
        if not ok:
            raise ValueError(
                f"{path}: credible_masses must be 2 to {_MAX_MASSES} numbers rising from 0 to 1"
            )
        masses = [float(m) for m in masses]
    before = record["val_nll_uncalibrated"]
    return {
        "temperature": float(t),
        "checkpoint": name,
        "val_nll": float(record["val_nll"]),
        "val_nll_uncalibrated": None if before is None else float(before),
        "num_val": count,
        "credible_masses": masses,
    }


def checkpoint_temperature(ckpt: Path) -> tuple[float, Any]:
    """The calibration fitted for the checkpoint file `ckpt` (`read_temperature` of the
    `TEMPERATURE_FILE` beside it): (temperature, level map or None); (1.0, None) without one, and
    with a logged warning when the file was fitted for another checkpoint (e.g. best.ckpt's
    temperature while loading last.ckpt).

    Raises:
        ValueError: as `read_temperature`.
    """
    record = read_temperature(ckpt.parent / TEMPERATURE_FILE)
    if record is None:
        return 1.0, None
    if record["checkpoint"] != ckpt.name:
        log.warning(
            "%s: the temperature %.4g was fitted for %s, not %s; the belief is left untempered "
            "(T = 1)",
            ckpt.parent / TEMPERATURE_FILE, record["temperature"], record["checkpoint"], ckpt.name,
        )  # fmt: skip
        return 1.0, None
    masses = record["credible_masses"]
    if masses is None:
        return record["temperature"], None
    import torch

    from rotlearn.bingham import LevelMap

    return record["temperature"], LevelMap(torch.tensor(masses, dtype=torch.float64))


def rebuildable(saved: Any) -> Any:
    """A saved run config without the nodes that no load builds: its loggers, and its callbacks
    but the OOD evaluation (`callbacks.ood`, which `rotlearn-eval` reuses). A logger or callback
    of the user's own that the run trained with then neither keeps it from loading nor is ever
    checked, imported or built."""
    if not isinstance(saved, dict):
        return saved  # `trusted_config` says what it is
    kept = {key: value for key, value in saved.items() if key != "logger"}
    if isinstance(saved.get("callbacks"), dict):
        kept["callbacks"] = {k: v for k, v in saved["callbacks"].items() if k == "ood"}
    return kept


def load_run(path: str | os.PathLike, task: str | None = None) -> SavedRun:
    """Read a rotlearn checkpoint for rebuilding its model.

    Args:
        path: a `.ckpt` file or a run directory (the weights its test scored:
            `tested_checkpoint`).
        task: if given, the run's `task` must be this ("rotation" or "autoencoder").

    Raises:
        FileNotFoundError: no such checkpoint.
        UnsafeCheckpointError: the file carries pickled code or is no checkpoint.
        UntrustedConfigError: the saved config names a `_target_` off the allowlist, or holds an
            interpolation; the message names the key path. Nothing was built.
        ValueError: not a rotlearn checkpoint, or of another task.
    """
    require("train", "load_run (a checkpoint's model is rebuilt from its Hydra config)")
    import torch

    ckpt = tested_checkpoint(path)
    checkpoint = load_checkpoint(ckpt)
    saved = checkpoint.get("rotlearn_config")
    if not saved:
        raise ValueError(f"{ckpt} is not a rotlearn checkpoint (no saved config)")
    config = trusted_config(rebuildable(saved), source=ckpt)
    state_dict = checkpoint.get("state_dict")
    if not isinstance(state_dict, dict) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state_dict.items()
    ):
        raise ValueError(f"{ckpt}: state_dict must map names to tensors")
    ood = read_thresholds(ckpt.parent / THRESHOLDS_FILE)
    if ood is None and checkpoint.get("rotlearn_ood") is not None:  # runs calibrated in place
        ood = _check_ood(checkpoint["rotlearn_ood"], ckpt, "rotlearn_ood")
    run = SavedRun(ckpt, config, state_dict, ood, *checkpoint_temperature(ckpt))
    if task is not None and run.task != task:
        names = {"autoencoder": "an auto-encoder", "rotation": "a rotation model"}
        is_, wanted = (names.get(t, f"task={t!r}") for t in (run.task, task))
        raise ValueError(f"{ckpt} is {is_} checkpoint, not {wanted}")
    return run
