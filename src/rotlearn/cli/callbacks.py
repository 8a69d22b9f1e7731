"""Hydra callbacks: a record of every job, so a sweep with a failed, killed or unstarted job loses
nothing.

Files: `<job dir>/status.json` (one job: RUNNING, COMPLETED, FAILED or INTERRUPTED, written by the
job itself), `<sweep dir>/planned_jobs.json` (every job of a basic-sweeper sweep, written once
before the first starts) and `<sweep dir>/jobs.json` (rebuilt from those two: jobs without a
status.json are PENDING).
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import shlex
import sys
from collections import Counter
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from rotlearn.io import WriteError, read_json, rewrite_in_place, write_json_atomic
from rotlearn.logs import logger_at_least

__all__ = [
    "JobStatusCallback",
    "ReportCallback",
    "end_failed_job",
    "planned_jobs",
    "record_job",
    "summarise_jobs",
    "tensorboard_command",
]

log = logging.getLogger("rotlearn")
PLANNED = "planned_jobs.json"
STATUSES = ("PENDING", "RUNNING", "COMPLETED", "FAILED", "INTERRUPTED", "UNREADABLE")
_BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"


@contextlib.contextmanager
def _sweep_lock(sweep_dir: Path):
    """An exclusive lock on `<sweep_dir>/.jobs.lock` (POSIX flock; no lock where there is none),
    so that parallel jobs rebuilding jobs.json never write a snapshot older than another's."""
    try:
        import fcntl
    except ImportError:  # Windows: the next rebuild repairs a lost update
        yield
        return
    with open(sweep_dir / ".jobs.lock", "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _started_jobs(sweep_dir: Path) -> list[dict[str, Any]]:
    jobs = []
    for path in sorted(sweep_dir.glob("*/status.json")):
        job = read_json(path)
        if not isinstance(job, dict):  # a job killed mid-write leaves no file, or a damaged one
            job = {"dir": str(path.parent), "status": "UNREADABLE", "error": f"cannot read {path}"}
        jobs.append(job)
    return jobs


def summarise_jobs(sweep_dir: str | Path) -> dict[str, Any]:
    """Rebuild `<sweep_dir>/jobs.json` from the jobs' `*/status.json` and `planned_jobs.json`
    (a planned job without a status.json is PENDING); returns the summary.

    The per-job files are the record (each written atomically by its own job, whatever the
    launcher); jobs.json is rebuilt from them under a lock, so a crashed or parallel sweep still
    adds up. The summary counts every status: completed, failed, interrupted, running, pending.
    """
    sweep_dir = Path(sweep_dir)
    sweep_dir.mkdir(parents=True, exist_ok=True)
    with _sweep_lock(sweep_dir):
        jobs = _started_jobs(sweep_dir)
        started = {job.get("num") for job in jobs} | {job.get("dir") for job in jobs}
        for job in read_json(sweep_dir / PLANNED) or []:
            if job.get("num") not in started and (job.get("dir") or "?") not in started:
                jobs.append({**job, "status": "PENDING"})
        jobs.sort(key=lambda job: (job.get("num") is None, job.get("num"), job.get("dir") or ""))
        counts = Counter(job.get("status") for job in jobs)
        summary = {
            "jobs": jobs,
            **{status.lower(): counts.get(status, 0) for status in STATUSES},
        }
        write_json_atomic(sweep_dir / "jobs.json", summary)
    return summary


def _job_dir(config: DictConfig, sweep_dir: Path, num: int) -> str | None:
    """A planned job's directory, when the sweep's subdir is Hydra's default (the job number)."""
    node = config.hydra.sweep._get_node("subdir")
    raw = node._value() if node is not None else None
    return str((sweep_dir / str(num)).resolve()) if raw == "${hydra.job.num}" else None


def planned_jobs(config: DictConfig) -> list[dict[str, Any]] | None:
    """Every job of a multirun with Hydra's basic sweeper, in its job order (as BasicSweeper
    expands `hydra.sweeper.params` and the command line); None for other sweepers (Optuna), whose
    jobs are not known ahead and are listed as they start."""
    if OmegaConf.select(config, "hydra.sweeper._target_") != _BASIC_SWEEPER:
        return None
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    params = OmegaConf.select(config, "hydra.sweeper.params") or {}
    arguments = [f"{k}={v}" for k, v in params.items()] + list(config.hydra.overrides.task)
    overrides = OverridesParser.create().parse_overrides(arguments)
    batches = BasicSweeper.split_arguments(overrides, None)
    sweep_dir = Path(config.hydra.sweep.dir)
    return [
        {"num": num, "dir": _job_dir(config, sweep_dir, num), "overrides": list(job)}
        for num, job in enumerate(job for batch in batches for job in batch)
    ]


def _write_status(path: Path, record: dict[str, Any]) -> None:
    """status.json, durably; on a full disk (or quota) rewritten in place instead, so that a run
    that failed for want of space still says so (`rotlearn.io.rewrite_in_place`)."""
    try:
        write_json_atomic(path, record)
    except WriteError as exc:
        if exc.errno not in (errno.ENOSPC, errno.EDQUOT) or not path.is_file():
            raise
        rewrite_in_place(path, (json.dumps(record, indent=2, sort_keys=True) + "\n").encode())


def record_job(job_dir: str | Path, status: str, **fields: Any) -> dict[str, Any]:
    """Write `<job_dir>/status.json` (status, the job's number and overrides when run by Hydra,
    `error`, and `fields`) and, in a multirun, rebuild the sweep's jobs.json and log where the
    sweep stands when the job ends. Returns the record."""
    hydra_cfg = HydraConfig.get() if HydraConfig.initialized() else None
    record = {
        "num": OmegaConf.select(hydra_cfg, "job.num") if hydra_cfg is not None else None,
        "dir": str(Path(job_dir).resolve()),
        "overrides": list(hydra_cfg.overrides.task) if hydra_cfg is not None else [],
        "status": status,
        "error": None,
        **fields,
    }
    _write_status(Path(job_dir) / "status.json", record)
    mode = OmegaConf.select(hydra_cfg, "mode") if hydra_cfg is not None else None
    if getattr(mode, "name", None) == "MULTIRUN":
        summary = summarise_jobs(hydra_cfg.sweep.dir)
        if status != "RUNNING":  # once a job, at its end
            log.info(
                "sweep so far: %d completed, %d failed, %d interrupted, %d running, %d pending",
                *(summary[k] for k in ("completed", "failed", "interrupted", "running", "pending")),
            )
    return record


def end_failed_job(run_dir: str | Path, exc: BaseException, prog: str) -> None:
    """End a single run that failed on its input or its machine (a config value, a file, a full
    disk): its status.json says FAILED with the cause, and the command ends with one line naming
    it (SystemExit, exit code 1) instead of a traceback. Returns without doing anything in a
    multirun (Hydra records the job FAILED and goes on with the next), on a rank other than 0,
    and with HYDRA_FULL_ERROR=1 (the traceback is kept)."""
    import os

    from hydra.types import RunMode

    from rotlearn.cli.rundir import is_child_rank

    hydra_cfg = HydraConfig.get() if HydraConfig.initialized() else None
    multirun = hydra_cfg is not None and hydra_cfg.mode == RunMode.MULTIRUN
    if multirun or os.environ.get("HYDRA_FULL_ERROR") == "1" or is_child_rank():
        return
    lines = str(exc).strip().splitlines()
    message = lines[0] if lines else type(exc).__name__
    try:
        record_job(run_dir, "FAILED", error=f"{type(exc).__name__}: {message}")
    except OSError as write_error:
        message += f" (status.json not written: {write_error})"
    log.error("%s", message)
    raise SystemExit(f"{prog}: {message} (run {run_dir}: FAILED)") from None


class JobStatusCallback(Callback):
    """Records every job: the sweep's planned jobs at the start of a multirun (PENDING), each job's
    `status.json` when it starts (RUNNING) and ends (COMPLETED, or FAILED with the error), and the
    sweep's `jobs.json` after each. (A signal's INTERRUPTED is written by `rotlearn.cli.train`.)"""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        jobs = planned_jobs(config)
        if jobs is None:
            return
        sweep_dir = Path(config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        write_json_atomic(sweep_dir / PLANNED, jobs)
        summarise_jobs(sweep_dir)

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        record_job(config.hydra.runtime.output_dir, "RUNNING")

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        job_dir = Path(config.hydra.runtime.output_dir)
        failed = job_return.status != JobStatus.COMPLETED
        error = getattr(job_return, "_return_value", None) if failed else None
        message = f"{type(error).__name__}: {error}" if error is not None else None
        if failed:
            log.error("job %s failed (%s); the other jobs' results are kept", job_dir, message)
        record_job(job_dir, "FAILED" if failed else "COMPLETED", error=message)


def tensorboard_command(folder: str | Path) -> str | None:
    """How to open TensorBoard on a run or sweep `folder` (relative to the working directory
    where it lies below it), quoted for the shell: the venv's `tensorboard --logdir` of a run's
    `tensorboard/` folder (its runs then read `<name>/train`, not `tensorboard/<name>/train`,
    whose stage a narrow runs panel cut off) or of a sweep folder (`<job>/tensorboard/...`);
    None where neither it nor a job of it holds a `tensorboard/` folder (logger=csv or none)."""
    folder = Path(folder)
    if (folder / "tensorboard").is_dir():
        folder = folder / "tensorboard"
    elif not any(folder.glob("*/tensorboard")):
        return None
    program = Path(sys.executable).parent / "tensorboard"
    shown = [str(program) if program.exists() else "tensorboard", str(folder)]
    for i, path in enumerate(shown):
        with contextlib.suppress(ValueError):
            shown[i] = str(Path(path).resolve().relative_to(Path.cwd()))
    logdir = f"./{shown[1]}" if shown[1].startswith("-") else shown[1]  # not read as a flag
    return f"{shlex.quote(shown[0])} --logdir {shlex.quote(logdir)}"


class ReportCallback(Callback):
    """Runs `rotlearn-report` on the sweep directory when a multirun ends. (Hydra skips this when
    a job failed; `rotlearn-report <dir>` then makes the same report, failures listed.)"""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        from rotlearn.report import make_report

        sweep_dir = config.hydra.sweep.dir
        try:
            with logger_at_least("tensorboard"):
                files = make_report(sweep_dir)
        except (OSError, ValueError) as exc:  # no runs, a failed write, a layout it refuses
            log.warning("no report: %s (the jobs' results are kept: rotlearn-report %s)",
                        exc, sweep_dir)  # fmt: skip
            return
        log.info("report: %s", files["report"])
        if command := tensorboard_command(sweep_dir):  # none for logger=csv or logger=none
            log.info("open TensorBoard on the sweep: %s", command)
