"""`rotlearn-train` (also `python -m rotlearn.train`): train, test, write the run's metrics.json.

Every component comes from the Hydra config with `hydra.utils.instantiate`; every file goes below
`paths.output_dir` (Hydra's run directory). See conf/train.yaml.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import signal
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import hydra
import lightning.pytorch as pl
import torch
from hydra.errors import InstantiationException
from lightning.fabric.plugins.environments import SLURMEnvironment
from lightning.pytorch.loggers import TensorBoardLogger
from omegaconf import DictConfig, OmegaConf

from rotlearn.checkpoint import load_checkpoint, resolve_checkpoint
from rotlearn.cli.callbacks import record_job
from rotlearn.cli.replay import saved_overrides
from rotlearn.cli.schemas import validate
from rotlearn.errors import ConfigError
from rotlearn.io import write_json_atomic
from rotlearn.lit import (
    AutoEncoderModule,
    EpochLosses,
    EpochTimer,
    InterruptRecorder,
    RotationRegressor,
)
from rotlearn.nets import ConvAutoEncoder
from rotlearn.paths import config_dir
from rotlearn.trust import UntrustedConfigError

__all__ = [
    "ConfigError",
    "RunInterrupted",
    "build",
    "divergence",
    "keep_earlier_records",
    "main",
    "resume_arguments",
    "train",
]

log = logging.getLogger("rotlearn")

# Lightning's advice that does not apply: batches are drawn on the device (no loader workers),
# and scalars are logged once per epoch on purpose.
for _pattern in (".*does not have many workers.*", ".*smaller than the logging interval.*"):
    warnings.filterwarnings("ignore", _pattern)


def _instantiate(cfg: DictConfig, key: str, **kwargs: Any) -> Any:
    """Instantiate the config node `key`; a component's `ConfigError` (its key relative to the
    node) is re-raised with the full key."""
    node = OmegaConf.select(cfg, key)
    if node is None:
        raise ConfigError(key, "is missing")
    try:
        return hydra.utils.instantiate(node, **kwargs)
    except InstantiationException as exc:  # Hydra wraps what the constructor raised
        if isinstance(exc.__cause__, ConfigError):
            raise exc.__cause__.within(key) from None
        raise


def _instantiate_all(cfg: DictConfig, key: str) -> list[Any]:
    node = OmegaConf.select(cfg, key) or {}
    return [_instantiate(cfg, f"{key}.{name}") for name in node]


def build(
    cfg: DictConfig,
) -> tuple[RotationRegressor | AutoEncoderModule, pl.LightningDataModule, pl.Trainer]:
    """Model, datamodule and trainer for a composed config (validated, seeds set first).

    `task=rotation` builds a `RotationRegressor`; `task=autoencoder` an `AutoEncoderModule`
    (paper section VI-C.1: no head, no loss), whose net must be `net=autoencoder`."""
    validate(cfg)
    task = cfg.get("task", "rotation")
    if task not in ("rotation", "autoencoder"):
        raise ConfigError("task", f"must be 'rotation' or 'autoencoder', got {task!r}")
    pl.seed_everything(cfg.seed, workers=True, verbose=False)
    datamodule = _instantiate(cfg, "data")
    head = _instantiate(cfg, "rep") if task == "rotation" else None
    net = _instantiate(cfg, "net")
    if isinstance(net, ConvAutoEncoder) != (task == "autoencoder"):
        raise ConfigError(
            "task",
            f"task={task} cannot train net {cfg.net._target_} "
            "(task=autoencoder goes with net=autoencoder, every other net with task=rotation)",
        )
    if task == "autoencoder":
        model = AutoEncoderModule(net=net, optimizer=_instantiate(cfg, "optim"))
    else:
        loss = _instantiate(cfg, "loss")
        optimizer = _instantiate(cfg, "optim")
        scheduler = _instantiate(cfg, "scheduler") if OmegaConf.select(cfg, "scheduler") else None
        model = RotationRegressor(
            net=net, head=head, loss=loss, optimizer=optimizer, scheduler=scheduler
        )
    model.run_config = OmegaConf.to_container(cfg, resolve=True)
    callbacks = _instantiate_all(cfg, "callbacks")
    # record keeping, whatever conf/callbacks says: signals (status.json) and per-epoch losses
    callbacks += [cb() for cb in (InterruptRecorder, EpochLosses)]
    trainer = _instantiate(
        cfg,
        "trainer",
        callbacks=callbacks,
        logger=_instantiate_all(cfg, "logger") or False,
    )
    return model, datamodule, trainer


def _flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(tree, dict):
        out: dict[str, Any] = {}
        for k, v in tree.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    value = tree if isinstance(tree, (int, float, str, bool)) or tree is None else str(tree)
    return {prefix[:-1]: value}


def _scalars(metrics: dict[str, Any]) -> dict[str, float]:
    return {k: float(v) for k, v in metrics.items() if torch.as_tensor(v).numel() == 1}


def _timing(trainer: pl.Trainer) -> dict[str, Any]:
    timers = [cb for cb in trainer.callbacks if isinstance(cb, EpochTimer)]
    times = timers[0].epoch_times if timers else []
    steady = times[1:]  # the first epoch carries one-off start-up costs
    return {
        "epoch_times_s": times,
        "epoch_time_s": sum(steady) / len(steady) if steady else math.nan,
    }


class RunInterrupted(SystemExit):
    """A signal stopped the run; the exit code is the shell's 128 + signal number (SIGTERM 143,
    SIGINT 130). `status` is what `train` wrote into the run's status.json."""

    def __init__(self, run_dir: Path, signal_name: str, last_epoch: int | None) -> None:
        self.run_dir, self.signal_name, self.last_epoch = run_dir, signal_name, last_epoch
        self.resume_command = f"rotlearn-train ckpt_path={run_dir.resolve()}"
        after = f"after epoch {last_epoch}" if last_epoch is not None else "before its first epoch"
        self.message = f"stopped by {signal_name} {after}; resume: {self.resume_command}"
        super().__init__(128 + int(signal.Signals[signal_name]))

    @property
    def status(self) -> dict[str, Any]:
        return {
            "signal": self.signal_name,
            "last_finished_epoch": self.last_epoch,
            "resume_command": self.resume_command,
            "error": self.message,
        }


def _last_finished_epoch(run_dir: Path, trainer: pl.Trainer) -> int | None:
    """The epoch (0-based, as Lightning counts) that `<run_dir>/checkpoints/last.ckpt` ends."""
    try:
        return int(load_checkpoint(run_dir)["epoch"])
    except (OSError, RuntimeError, KeyError, ValueError):
        done = trainer.fit_loop.epoch_progress.current.completed
        return done - 1 if done else None


@contextlib.contextmanager
def _interruptions_recorded(trainer: pl.Trainer, run_dir: Path):
    """Turn a stop by SIGTERM or SIGINT (seen by the trainer's `InterruptRecorder`) into a
    status.json with status INTERRUPTED in `run_dir` and a `RunInterrupted` exit; anything else
    propagates unchanged."""
    try:
        yield
    except (SystemExit, KeyboardInterrupt):
        recorders = [cb for cb in trainer.callbacks if isinstance(cb, InterruptRecorder)]
        name = recorders[0].signal_name if recorders else None
        if name is None:
            raise
        stop = RunInterrupted(run_dir, name, _last_finished_epoch(run_dir, trainer))
        if trainer.is_global_zero:
            record_job(run_dir, "INTERRUPTED", **stop.status)
        log.warning("%s: %s", run_dir, stop.message)
        raise stop from None


def _requeued_on_slurm() -> bool:
    """A SLURM job that was requeued (preemption, time-out) and runs again in its own directory:
    it continues that run (Lightning's hpc checkpoint, else last.ckpt) instead of refusing it."""
    restarts = os.environ.get("SLURM_RESTART_COUNT", "0")
    return restarts.isdigit() and int(restarts) > 0 and SLURMEnvironment.detect()


def _checkpoint_to_resume(cfg: DictConfig, run_dir: Path) -> str | None:
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


def divergence(
    metrics: dict[str, Any], train_losses: Sequence[float], factor: float = 100.0
) -> list[str]:
    """Why a run counts as diverged (an empty list: it did not).

    Two signs: the final test error (`test/err_mean`) is worse than predicting the identity
    (`test/identity_err_mean`), or the last epoch's mean training loss is more than `factor` times
    its lowest epoch value (for a lowest value <= 0, as a Bingham NLL can be: more than `factor`
    times its magnitude above it), or is not finite."""
    reasons = []
    err = metrics.get("test/err_mean")
    identity = metrics.get("test/identity_err_mean")
    if err is not None and identity is not None and not err <= identity:
        reasons.append(
            f"final test error {err:.2f} deg is worse than predicting the identity "
            f"({identity:.2f} deg)"
        )
    if train_losses:
        last, lowest = train_losses[-1], min(train_losses)
        grew = last > factor * lowest if lowest > 0 else last - lowest > factor * abs(lowest)
        if not math.isfinite(last) or grew:
            reasons.append(
                f"training loss grew from {lowest:.4g} (lowest epoch) to {last:.4g} (last epoch)"
            )
    return reasons


def _epoch_losses(trainer: pl.Trainer) -> list[float]:
    found = [cb for cb in trainer.callbacks if isinstance(cb, EpochLosses)]
    return found[0].losses if found else []


def train(cfg: DictConfig) -> dict[str, Any]:
    """Fit, test and write `metrics.json` in `cfg.paths.output_dir`; returns those metrics.

    The config is validated by `build`, before anything is trained. A SIGTERM or SIGINT during
    `fit` or `test` stops the run at a batch boundary: `checkpoints/last.ckpt` stays the end of
    the last finished epoch, `status.json` says INTERRUPTED (signal, that epoch, the resume
    command) and `RunInterrupted` exits 143 (SIGTERM) or 130 (SIGINT). `metrics.json` records
    `diverged` (see `divergence`), with a WARNING naming why."""
    run_dir = Path(cfg.paths.output_dir)
    resume = _checkpoint_to_resume(cfg, run_dir)
    torch.set_float32_matmul_precision(cfg.float32_matmul_precision)
    model, datamodule, trainer = build(cfg)

    with _interruptions_recorded(trainer, run_dir):
        trainer.fit(model, datamodule=datamodule, ckpt_path=resume, weights_only=True)
        metrics = _scalars(trainer.callback_metrics)
        best_path = (
            trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
        )
        ckpt_path = best_path if cfg.test_ckpt == "best" and best_path else None
        trainer.test(
            model, datamodule=datamodule, ckpt_path=ckpt_path, verbose=False, weights_only=True
        )
    metrics.update(_scalars(trainer.callback_metrics))

    metrics = {k: v for k, v in metrics.items() if not k.startswith("time/")}
    task = cfg.get("task", "rotation")
    metrics.update(
        {
            "epochs": trainer.current_epoch,
            "global_step": trainer.global_step,
            "seed": cfg.seed,
            "data_seed": OmegaConf.select(cfg, "data.seed"),
            "task": task,
            "tested_weights": "best" if ckpt_path else "last",
        }
    )
    if task == "rotation":
        metrics["rep"] = OmegaConf.select(cfg, "rep.name")
    checkpoints = trainer.checkpoint_callback
    if checkpoints and checkpoints.best_model_score is not None:  # best/val_err_mean, best/val_loss
        metrics[f"best/{checkpoints.monitor.replace('/', '_')}"] = float(
            checkpoints.best_model_score
        )
    reasons = divergence(metrics, _epoch_losses(trainer))
    for reason in reasons:
        log.warning("%s diverged: %s", run_dir, reason)
    metrics["diverged"] = bool(reasons)
    if trainer.is_global_zero:
        # metrics.json holds only what the config and seeds determine (identical on a rerun);
        # wall-clock times go beside it.
        write_json_atomic(run_dir / "timing.json", _timing(trainer))
        test_errors = getattr(model, "test_errors", None)  # the auto-encoder has none
        if test_errors is not None:  # per-sample errors, for box plots (paper Fig. 4)
            write_json_atomic(run_dir / "test_errors.json", test_errors.tolist())
        write_json_atomic(run_dir / "metrics.json", metrics)
        hp_metrics = {
            f"hp/{k.replace('/', '_')}": v
            for k, v in metrics.items()
            if "/err_" in k or "/recon_" in k
        }
        params = _flatten(OmegaConf.to_container(cfg, resolve=True))
        for logger in trainer.loggers:
            if isinstance(logger, TensorBoardLogger):  # its hparams tab shows these metrics
                logger.log_hyperparams(params, hp_metrics)
            else:
                logger.log_hyperparams(params)
            logger.finalize("success")
    return metrics


def _report(cfg: DictConfig, metrics: dict[str, Any]) -> None:
    run_dir = Path(cfg.paths.output_dir)
    try:
        shown = run_dir.resolve().relative_to(Path.cwd())
    except ValueError:
        shown = run_dir
    tensorboard = Path(sys.executable).parent / "tensorboard"
    tb = str(tensorboard) if tensorboard.exists() else "tensorboard"
    with contextlib.suppress(ValueError):
        tb = str(Path(tb).relative_to(Path.cwd()))
    if metrics.get("task") == "autoencoder":
        log.info(
            "test reconstruction error (auto-encoder, %s weights): mean L1 %.4f",
            metrics.get("tested_weights"),
            metrics.get("test/recon_mean", math.nan),
        )
    else:
        log.info(
            "test error (%s head, %s weights): mean %.3f deg, median %.3f deg, p90 %.3f deg",
            metrics.get("rep"),
            metrics.get("tested_weights"),
            metrics.get("test/err_mean", math.nan),
            metrics.get("test/err_median", math.nan),
            metrics.get("test/err_p90", math.nan),
        )
        log.info(
            'baseline "predict identity": mean %.3f deg, median %.3f deg',
            metrics.get("test/identity_err_mean", math.nan),
            metrics.get("test/identity_err_median", math.nan),
        )
    log.info("run directory: %s (metrics.json, checkpoints/, tensorboard/)", shown)
    log.info("open TensorBoard: %s --logdir %s", tb, shown)


# What a completed run may be resumed with: more epochs, and nothing that changes its results.
_ALLOWED_ON_A_COMPLETED_RUN = ("trainer.max_epochs", "trainer.enable_progress_bar")
# The records of one attempt at a run; a resume keeps the earlier ones in history/<n>/.
_RECORDS = ("metrics.json", "status.json", "timing.json", "test_errors.json")


def _refuse(message: str) -> SystemExit:
    return SystemExit(f"rotlearn-train: {message}")


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _is_completed(run_dir: Path) -> bool:
    """A run that finished (metrics.json written, or status.json says COMPLETED)."""
    status = _read_json(run_dir / "status.json") or {}
    return (run_dir / "metrics.json").exists() or status.get("status") == "COMPLETED"


def _epochs_finished(run_dir: Path) -> int:
    """How many epochs a run trained: metrics.json's `epochs`, else last.ckpt's epoch + 1."""
    metrics = _read_json(run_dir / "metrics.json") or {}
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
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():  # inside another Hydra app: `build` validates
        return
    overrides = [a for a in args if not a.lstrip("+~").startswith(("hydra.", "hydra/"))]
    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            validate(compose("train", [*overrides, f"paths.output_dir={run_dir}"]))
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


@hydra.main(version_base="1.3", config_path=str(config_dir()), config_name="train")
def _hydra_main(cfg: DictConfig) -> float:
    metrics = train(cfg)
    _report(cfg, metrics)
    # what sweepers (Optuna) minimise: the validation median error, never a test number
    return metrics.get("val/err_median", metrics.get("val/loss", math.nan))


def main() -> float:
    """Entry point of `rotlearn-train`; returns the validation median error (for sweepers)."""
    argv = sys.argv[1:]
    args = resume_arguments(argv)
    if args != argv:  # a resume that will train: its last argument is hydra.run.dir=<run dir>
        kept = keep_earlier_records(Path(args[-1].split("=", 1)[1]))
        if kept is not None:
            print(f"rotlearn-train: the run's earlier records are kept in {kept}", file=sys.stderr)
    sys.argv[1:] = args
    return _hydra_main()


if __name__ == "__main__":
    main()
