"""One process at a time per run directory: an exclusive `fcntl` lock on `<run>/.rotlearn.lock`.

A process that trains a run (a new one, or a resume) holds the lock until it ends; a second
process that would train the same run is refused in one line naming the holder (pid, host, start
time and command, as the holder wrote them into the lock file). The kernel drops the lock when its
holder dies however it dies (SIGKILL, a crash), so a lock file left behind by a dead process is
stale: the next process takes the lock and says whose it was. Within one process the lock is
re-entrant (the resume check before Hydra starts and the training inside it share it).
"""

from __future__ import annotations

import atexit
import contextlib
import json
import logging
import os
import socket
import sys
import time
from pathlib import Path
from typing import IO, Any

__all__ = ["LOCK_FILE", "RunLockedError", "check_free", "hold_run", "release_run"]

LOCK_FILE = ".rotlearn.lock"
log = logging.getLogger("rotlearn")
_HELD: dict[Path, IO[str]] = {}  # run directory (resolved) -> the open, locked lock file


class RunLockedError(RuntimeError):
    """Another process holds the run's lock; the message names the run and the holder."""


def _describe(holder: dict[str, Any] | None) -> str:
    """Who holds (or held) a run's lock, from its lock file: data a received run may carry, so
    each field is shown as plain text of at most 200 characters (control characters dropped),
    and a start time that is no time is "?"."""
    if not holder:
        return "another process (it has not yet written who it is)"
    try:
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(float(holder.get("started"))))
    except (TypeError, ValueError, OverflowError, OSError):  # not a number of seconds
        when = "?"
    pid, host, command = (_shown(holder.get(key)) for key in ("pid", "host", "command"))
    return f"pid {pid} on {host} since {when} ({command})"


def _shown(value: Any) -> str:
    text = (
        "".join(c for c in str(value)[:200] if c.isprintable()) if value not in (None, "") else ""
    )
    return text or "?"


def _read_holder(handle: IO[str]) -> dict[str, Any] | None:
    try:
        handle.seek(0)
        data = json.loads(handle.read(4096))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _open_lock_file(path: Path) -> IO[str]:
    """The lock file, opened for reading and writing without following a symlink, created with
    the mode the umask allows; refused if it is not a regular file."""
    import stat

    from rotlearn.io import UnreadableFileError

    flags = os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags | getattr(os, "O_NONBLOCK", 0), 0o666)
    except OSError as exc:
        raise UnreadableFileError(
            f"{path}: cannot be opened as a lock file ({exc.strerror})"
        ) from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise UnreadableFileError(f"{path}: not a regular file; it cannot be a lock file")
    return os.fdopen(fd, "r+", encoding="utf-8")


def hold_run(run_dir: str | os.PathLike, command: str | None = None) -> None:
    """Take the run's lock for the rest of this process (or until `release_run`).

    Args:
        run_dir: the run directory (it must exist).
        command: what this process does, for the message a refused process prints (default:
            its command line).

    Raises:
        RunLockedError: another process holds it: "<run> is in use by pid ... on ... since ...
            (<command>)".
        UnreadableFileError: the lock file is a symlink or not a regular file.
    """
    try:
        import fcntl
    except ImportError:  # Windows: no advisory locks; one process per run is the user's care
        return
    run = Path(run_dir).resolve()
    if run in _HELD:
        return
    handle = _open_lock_file(run / LOCK_FILE)
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = _read_holder(handle)
        handle.close()
        raise RunLockedError(f"{run} is in use by {_describe(holder)}") from None
    previous = _read_holder(handle)  # a clean release empties the file: this holder died
    if previous:
        log.warning("%s: took over the stale lock of %s (it ended without releasing it)",
                    run, _describe(previous))  # fmt: skip
    me = {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "started": time.time(),
        "command": command or " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
    }
    handle.seek(0)
    handle.truncate()
    handle.write(json.dumps(me) + "\n")
    handle.flush()
    _HELD[run] = handle


def check_free(run_dir: str | os.PathLike) -> None:
    """Refuse if another process holds the run's lock; creates and changes nothing (a run
    without a lock file is free: every holder creates one).

    Raises:
        RunLockedError: naming the run and the holder.
    """
    try:
        import fcntl
    except ImportError:
        return
    run = Path(run_dir).resolve()
    path = run / LOCK_FILE
    if run in _HELD or not os.path.lexists(path):
        return
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    try:
        fd = os.open(path, flags | getattr(os, "O_CLOEXEC", 0))
    except OSError:
        return  # a symlink or unreadable: the run tree check names it
    with os.fdopen(fd, "r", encoding="utf-8") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            raise RunLockedError(f"{run} is in use by {_describe(_read_holder(handle))}") from None


def release_run(run_dir: str | os.PathLike) -> None:
    """Drop this process's lock on the run, if it holds one (the file stays, emptied: a holder
    named in it is one that died holding the lock)."""
    handle = _HELD.pop(Path(run_dir).resolve(), None)
    if handle is not None:
        with contextlib.suppress(OSError):
            handle.truncate(0)
            handle.flush()
        handle.close()  # closing the file releases the flock


@atexit.register
def _release_all() -> None:
    for run in list(_HELD):
        release_run(run)
