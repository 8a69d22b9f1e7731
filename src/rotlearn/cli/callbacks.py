"""Hydra callbacks: a record of every job, so a sweep with a failed job loses nothing."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from rotlearn.io import write_json_atomic

__all__ = ["JobStatusCallback", "ReportCallback", "summarise_jobs"]

log = logging.getLogger("rotlearn")


def summarise_jobs(sweep_dir: str | Path) -> dict[str, Any]:
    """Collect `<sweep_dir>/*/status.json` into `<sweep_dir>/jobs.json`; returns the summary.

    The per-job files are the record (each written atomically by its own job, whatever the
    launcher); jobs.json is rebuilt from them, so a crashed or parallel sweep still adds up.
    """
    sweep_dir = Path(sweep_dir)
    jobs = []
    for path in sorted(sweep_dir.glob("*/status.json")):
        try:
            jobs.append(json.loads(path.read_text()))
        except (OSError, json.JSONDecodeError) as exc:  # a job killed mid-write leaves no file
            jobs.append({"dir": str(path.parent), "status": "UNREADABLE", "error": repr(exc)})
    jobs.sort(key=lambda job: (job.get("num") is None, job.get("num"), job.get("dir")))
    failed = [job for job in jobs if job.get("status") != "COMPLETED"]
    summary = {"jobs": jobs, "completed": len(jobs) - len(failed), "failed": len(failed)}
    write_json_atomic(sweep_dir / "jobs.json", summary)
    return summary


class JobStatusCallback(Callback):
    """Writes `status.json` (COMPLETED or FAILED, with the error) in every job's directory and,
    in a multirun, refreshes the sweep's `jobs.json` and logs which jobs failed."""

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        hydra_cfg = config.hydra
        job_dir = Path(hydra_cfg.runtime.output_dir)
        failed = job_return.status != JobStatus.COMPLETED
        error = getattr(job_return, "_return_value", None) if failed else None
        status = {
            "num": hydra_cfg.job.get("num"),
            "dir": str(job_dir),
            "overrides": list(job_return.overrides or []),
            "status": "FAILED" if failed else "COMPLETED",
            "error": f"{type(error).__name__}: {error}" if error is not None else None,
        }
        write_json_atomic(job_dir / "status.json", status)
        if hydra_cfg.mode.name == "MULTIRUN":
            summary = summarise_jobs(hydra_cfg.sweep.dir)
            if failed:
                log.error(
                    "job %s failed (%s); the other jobs' results are kept", job_dir, status["error"]
                )
            log.info(
                "sweep so far: %d completed, %d failed", summary["completed"], summary["failed"]
            )


class ReportCallback(Callback):
    """Runs `rotlearn-report` on the sweep directory when a multirun ends. (Hydra skips this when
    a job failed; `rotlearn-report <dir>` then makes the same report, failures listed.)"""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        from rotlearn.cli.report import make_report

        try:
            files = make_report(config.hydra.sweep.dir)
        except FileNotFoundError as exc:
            log.warning("no report: %s", exc)
            return
        log.info("report: %s", files["report"])
