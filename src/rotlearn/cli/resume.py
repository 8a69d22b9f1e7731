"""Continuing a run: `rotlearn-train ckpt_path=<run dir | .ckpt | last>`.

`resume_arguments` rewrites the command line so that Hydra continues the run in its own directory
with its own saved overrides (checked as untrusted data: `rotlearn.cli.replay`). Every refusal
happens there, before Hydra writes anything, so a refused resume leaves the run byte-identical.
`keep_earlier_records` moves an attempt's records into `history/<n>/` before a resume trains, and
`checkpoint_to_resume` picks the checkpoint `fit` starts from (a requeued SLURM job continues its
own run).
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
from pathlib import Path

from lightning.fabric.plugins.environments import SLURMEnvironment
from omegaconf import DictConfig

from rotlearn.checkpoint import load_checkpoint, resolve_checkpoint
from rotlearn.cli.replay import saved_overrides
from rotlearn.io import read_json
from rotlearn.trust import UntrustedConfigError

__all__ = ["checkpoint_to_resume", "keep_earlier_records", "resume_arguments"]

log = logging.getLogger("rotlearn")


def _requeued_on_slurm() -> bool:
    """A SLURM job that was requeued (preemption, time-out) and runs again in its own directory:
    it continues that run (Lightning's hpc checkpoint, else last.ckpt) instead of refusing it."""
    restarts = os.environ.get("SLURM_RESTART_COUNT", "0")
    return restarts.isdigit() and int(restarts) > 0 and SLURMEnvironment.detect()


def checkpoint_to_resume(cfg: DictConfig, run_dir: Path) -> str | None:
    """The checkpoint `fit` starts from (None: a fresh run, or Lightning's own hpc checkpoint);
    refuses a finished run or a run directory that already holds another run."""
    if (run_dir / "metrics.json").exists():
        raise FileExistsError(
            f"{run_dir} holds a finished run (metrics.json); it is never rewritten"
        )
    resume = cfg.get("ckpt_path")
    if resume:
        resume = str(resolve_checkpoint(resume))
        log.info("resuming from %s", resume)
        return resume
    if (run_dir / "checkpoints").exists():
        if _requeued_on_slurm():
            if list(run_dir.glob("hpc_ckpt_*.ckpt")):
                return None  # Lightning restores its SIGUSR1 (hpc) checkpoint itself
            last = run_dir / "checkpoints" / "last.ckpt"
            return str(last) if last.is_file() else None
        raise FileExistsError(
            f"{run_dir} already holds a run; rotlearn never overwrites one (to continue it: "
            f"ckpt_path={run_dir})"
        )
    return None


# What a completed run may be resumed with: more epochs, and nothing that changes its results.
_ALLOWED_ON_A_COMPLETED_RUN = ("trainer.max_epochs", "trainer.enable_progress_bar")
# The records of one attempt at a run; a resume keeps the earlier ones in history/<n>/.
_RECORDS = ("metrics.json", "status.json", "timing.json", "test_errors.json")


def _refuse(message: str) -> SystemExit:
    return SystemExit(f"rotlearn-train: {message}")


def _is_completed(run_dir: Path) -> bool:
    """A run that finished (metrics.json written, or status.json says COMPLETED)."""
    status = read_json(run_dir / "status.json") or {}
    return (run_dir / "metrics.json").exists() or status.get("status") == "COMPLETED"


def _epochs_finished(run_dir: Path) -> int:
    """How many epochs a run trained: metrics.json's `epochs`, else last.ckpt's epoch + 1."""
    metrics = read_json(run_dir / "metrics.json") or {}
    if isinstance(metrics.get("epochs"), int):
        return metrics["epochs"]
    try:
        return int(load_checkpoint(run_dir)["epoch"]) + 1
    except (OSError, RuntimeError, KeyError, ValueError):
        return 0


def _newest_resumable_run(root: Path) -> Path:
    """The newest run under `root` with a last.ckpt that is not COMPLETED (named on stderr)."""
    runs = sorted(p.parent.parent for p in root.glob("*/checkpoints/last.ckpt"))
    completed = [run for run in runs if _is_completed(run)]
    resumable = [run for run in runs if run not in completed]
    if not resumable:
        why = (
            f"; {len(completed)} have one but are COMPLETED (newest: {completed[-1]})"
            if completed
            else ""
        )
        raise _refuse(
            f"ckpt_path=last, but no run under {root} can be resumed (a last.ckpt and not "
            f"COMPLETED){why}. A completed run only trains longer: "
            "ckpt_path=<run dir> trainer.max_epochs=<more epochs>"
        )
    skipped = [run for run in completed if run.name > resumable[-1].name]
    note = f"; skipped {len(skipped)} newer COMPLETED run(s)" if skipped else ""
    print(f"rotlearn-train: ckpt_path=last: resuming {resumable[-1]}{note}", file=sys.stderr)
    return resumable[-1]  # run directories are named by their start time


def _checkpoint_of(value: str, runs_root: Path) -> Path:
    """The checkpoint file that `ckpt_path=<value>` names (`last`: the newest resumable run)."""
    if value == "last":
        return resolve_checkpoint(_newest_resumable_run(runs_root))
    try:
        return resolve_checkpoint(value)
    except FileNotFoundError as exc:
        raise _refuse(f"ckpt_path: {exc}") from None


def _saved_overrides(run_dir: Path) -> list[str]:
    """The run's own command-line overrides, read from `<run_dir>/.hydra/overrides.yaml`
    (without its ckpt_path): the settings a resume continues with. The run directory is untrusted
    data: they pass the allowlist gate (`rotlearn.cli.replay.saved_overrides`) first."""
    try:
        return [o for o in saved_overrides(run_dir) if not o.startswith("ckpt_path=")]
    except (FileNotFoundError, UntrustedConfigError) as exc:
        raise _refuse(f"ckpt_path: {exc}") from None


def _refuse_rewriting_a_completed_run(run_dir: Path, previous: list[str], new: list[str]) -> None:
    """A COMPLETED run is resumed only to train longer: `trainer.max_epochs` above the epochs it
    finished, and no override that changes its other settings."""
    if not _is_completed(run_dir):
        return
    done = _epochs_finished(run_dir)
    longer = f"to train it longer: rotlearn-train ckpt_path={run_dir} trainer.max_epochs=<more>"
    head = f"refusing to resume {run_dir}: it is COMPLETED ({done} epochs) and never rewritten"
    changed = [
        o
        for o in new
        if o not in previous and o.split("=", 1)[0].lstrip("+~") not in _ALLOWED_ON_A_COMPLETED_RUN
    ]
    if changed:
        raise _refuse(
            f"{head}; a completed run only trains longer, but this command also sets "
            f"{' '.join(changed)} (start a new run for other settings; {longer})"
        )
    epochs = [o.split("=", 1)[1] for o in new if o.startswith("trainer.max_epochs=")]
    if not epochs or not epochs[-1].isdigit() or int(epochs[-1]) <= done:
        given = f" (trainer.max_epochs={epochs[-1]} is not above {done})" if epochs else ""
        raise _refuse(f"{head}{given}; {longer}, above {done}")


def _refuse_an_invalid_config(run_dir: Path, args: list[str]) -> None:
    """Compose and validate the resumed run's config before Hydra writes anything into it."""
    from rotlearn.config import command_line

    try:
        command_line(args, str(run_dir))
    except Exception as exc:  # any composition or validation error: nothing was written
        raise _refuse(f"refusing to resume {run_dir}: {exc}") from None


def resume_arguments(argv: list[str], runs_root: Path = Path("outputs/runs")) -> list[str]:
    """Rewrite a command line with `ckpt_path=...` so that Hydra continues that run in its own
    directory with its own overrides: `[saved overrides, new overrides, ckpt_path=<file>,
    hydra.run.dir=<run dir>]`. Other command lines are returned unchanged.

    Every refusal happens here, before Hydra writes into the run directory, so a refused resume
    leaves it byte-identical (SystemExit naming the run): -m, no such checkpoint, not a rotlearn
    run, a COMPLETED run resumed with other settings or without more `trainer.max_epochs`, a
    config that does not compose or validate. `ckpt_path=last` is the newest run under
    `runs_root` that has a last.ckpt and is not COMPLETED (named on stderr)."""
    values = [a.split("=", 1)[1] for a in argv if a.startswith("ckpt_path=")]
    if not values or values[-1] in ("", "null", "None"):
        return argv
    if "-m" in argv or "--multirun" in argv:
        raise _refuse("ckpt_path resumes one run; it cannot be used with -m")
    ckpt = _checkpoint_of(values[-1], runs_root)
    run_dir = ckpt.parent.parent if ckpt.parent.name == "checkpoints" else ckpt.parent
    # the run's saved overrides: read here, in one step, before they are used
    previous = _saved_overrides(run_dir)
    new = [a for a in argv if not a.startswith("ckpt_path=")]
    _refuse_rewriting_a_completed_run(run_dir, previous, new)
    args = [*previous, *new, f"ckpt_path={ckpt.resolve()}", f"hydra.run.dir={run_dir.resolve()}"]
    _refuse_an_invalid_config(run_dir, args)
    return args


def keep_earlier_records(run_dir: Path) -> Path | None:
    """Before a resume trains: move the run's records (metrics.json, status.json, timing.json,
    test_errors.json) and copy its `.hydra/*.yaml` into `<run_dir>/history/<n>/` (n = 1, 2, ...
    per resume), so the new attempt never overwrites them. Returns that folder (None when the
    run had no records)."""
    records = [run_dir / name for name in _RECORDS if (run_dir / name).exists()]
    configs = sorted((run_dir / ".hydra").glob("*.yaml"))
    if not records and not configs:
        return None
    history = run_dir / "history"
    n = 1 + max((int(p.name) for p in history.glob("*") if p.name.isdigit()), default=0)
    target = history / str(n)
    (target / ".hydra").mkdir(parents=True)
    for path in configs:  # copied: the run keeps a config until Hydra writes the new one
        shutil.copy2(path, target / ".hydra" / path.name)
    for path in records:
        os.replace(path, target / path.name)
    return target
