"""Train and test one run of a composed config: `build` and `train`, run by `rotlearn-train`
(`rotlearn.cli.train`, the entry point, which also re-exports them).

Every component comes from the Hydra config with `hydra.utils.instantiate` (`build`); every file
goes below `paths.output_dir` (Hydra's run directory), the records written by
`rotlearn.lit.RunRecords`. Resuming is `rotlearn.cli.resume`. See conf/train.yaml; the config is
validated and the model built by `rotlearn.config`.
"""

from __future__ import annotations

import contextlib
import logging
import math
import signal
import warnings
from pathlib import Path
from typing import Any

import hydra
import lightning.pytorch as pl
import torch
from hydra.errors import InstantiationException
from omegaconf import DictConfig, ListConfig, OmegaConf

from rotlearn import config
from rotlearn.checkpoint import load_checkpoint
from rotlearn.cli.callbacks import PLANNED, record_job, tensorboard_command
from rotlearn.cli.replay import resume_word
from rotlearn.cli.resume import checkpoint_to_resume
from rotlearn.cli.rundir import is_child_rank, keys_to_give_again
from rotlearn.errors import ConfigError
from rotlearn.io import plain_name, read_json
from rotlearn.lit import (
    CheckpointStateGuard,
    EpochLosses,
    InterruptRecorder,
    ModelSummary,
    PostHocCalibration,
    ProgressBar,
    RunCheckpointIO,
    RunRecords,
    find_callback,
)
from rotlearn.locks import hold_run, release_run
from rotlearn.report.identity import hparams_record, run_name, swept_keys
from rotlearn.report.tensorboard import EVENTS_DIR, event_runs

__all__ = ["ConfigError", "RunInterrupted", "build", "report", "train"]

log = logging.getLogger("rotlearn")

# Lightning's advice that does not apply: batches are drawn on the device (no loader workers),
# and scalars are logged once per epoch on purpose.
for _pattern in (".*does not have many workers.*", ".*smaller than the logging interval.*"):
    warnings.filterwarnings("ignore", _pattern)
# A resume continues in the run's own checkpoints/ and csv/ (a new run never writes into an
# existing folder: rotlearn refuses it), which Lightning warns of on every resume, the CSV logger
# saying that the earlier rows "will be deleted": they are kept (tests/cli/test_resume.py).
warnings.filterwarnings(
    "ignore", message=r"(Checkpoint|Experiment logs) directory .* exists and is not empty"
)
# Lightning's own use of a torch API that torch deprecates (its loops flatten every batch), which
# nobody but Lightning can act on.
warnings.filterwarnings(
    "ignore",
    message=r"`isinstance\(treespec, LeafSpec\)` is deprecated",
    category=FutureWarning,
    module=r"lightning\.pytorch\.utilities\._pytree",
)


class _WithoutCloudTips(logging.Filter):
    """Drops Lightning's tips to install its cloud services' packages (litlogger, litmodels),
    printed on every run; Lightning has no switch (Lightning-AI/pytorch-lightning#21294)."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        advert = "litlogger" in message or "litmodels" in message
        return not (message.startswith("💡 Tip:") and advert)


logging.getLogger("lightning.pytorch.utilities.rank_zero").addFilter(_WithoutCloudTips())


def _instantiate(cfg: DictConfig, key: str, **kwargs: Any) -> Any:
    """Instantiate the config node `key`; a component's `ConfigError` (its key relative to the
    node) is re-raised with the full key."""
    try:
        return hydra.utils.instantiate(OmegaConf.select(cfg, key), **kwargs)
    except InstantiationException as exc:  # Hydra wraps what the constructor raised
        if isinstance(exc.__cause__, ConfigError):
            raise exc.__cause__.within(key) from None
        raise


def _instantiate_all(cfg: DictConfig, key: str, **kwargs: Any) -> list[Any]:
    """Every entry of the node `key` (`logger`, `callbacks`); `kwargs`: entry name -> keyword
    arguments for that entry."""
    node = OmegaConf.select(cfg, key) or {}
    return [_instantiate(cfg, f"{key}.{name}", **kwargs.get(str(name), {})) for name in node]


class _Runtime:
    """What Hydra's runtime says about this run (nothing for a config composed without it): its
    command-line overrides, the option chosen in each config group, and, in a sweep, the job's
    number and the keys the sweep varies."""

    def __init__(self) -> None:
        from hydra.core.hydra_config import HydraConfig

        self.overrides: list[str] = []
        self.choices: dict[str, str] = {}
        self.job_num: int | None = None
        self.swept: list[str] | None = None
        if not HydraConfig.initialized():
            return
        hydra_cfg = HydraConfig.get()
        self.overrides = [str(o) for o in hydra_cfg.overrides.task]
        choices = OmegaConf.to_container(hydra_cfg.runtime.choices)
        self.choices = {str(k): str(v) for k, v in choices.items() if v is not None}
        if getattr(hydra_cfg.mode, "name", None) == "MULTIRUN":
            self.job_num = int(OmegaConf.select(hydra_cfg, "job.num", default=0) or 0)
            self.swept = self._swept(hydra_cfg)

    @staticmethod
    def _swept(hydra_cfg: DictConfig) -> list[str]:
        """The keys the sweep varies: from its planned jobs (basic sweeper), else the keys of
        `hydra.sweeper.params` (Optuna and other sweepers)."""
        planned = read_json(Path(hydra_cfg.sweep.dir) / PLANNED)
        if isinstance(planned, list) and planned:
            jobs = [job.get("overrides") or [] for job in planned if isinstance(job, dict)]
            return swept_keys(jobs)
        params = OmegaConf.select(hydra_cfg, "sweeper.params") or {}
        return [str(key) for key in params]


_RUN_LOGGERS = (
    "rotlearn.lit.TensorBoardRunLogger",
    "rotlearn.lit.tensorboard.TensorBoardRunLogger",
)


def _tensorboard_name(cfg: DictConfig, config: dict[str, Any], runtime: _Runtime) -> str:
    """The name of the run in TensorBoard (its folder below `<run>/tensorboard/`): the one a
    resumed run already has, else its overrides (in a sweep: the swept ones), e.g.
    `rep=a,optim.lr=0.001` (`rotlearn.report.identity.run_name`)."""
    existing = event_runs(Path(cfg.paths.output_dir))
    if len(existing) == 1 and existing[0].name != EVENTS_DIR:
        return plain_name(existing[0].name, where=str(existing[0]))
    return run_name(config, runtime.overrides, runtime.choices, runtime.swept)


def _loggers(cfg: DictConfig, config: dict[str, Any], runtime: _Runtime) -> list[Any]:
    """The configured loggers; a `TensorBoardRunLogger` without a version gets the run's name."""
    node = OmegaConf.select(cfg, "logger") or {}
    named = {}
    for name in node:
        entry = node[name]
        target = entry.get("_target_") if isinstance(entry, DictConfig) else None
        if target in _RUN_LOGGERS and entry.get("version") in (None, ""):
            named[str(name)] = {"version": _tensorboard_name(cfg, config, runtime)}
    return _instantiate_all(cfg, "logger", **named)


def check_buildable(cfg: DictConfig) -> None:
    """Build what checks its values in its constructor, of a validated config (the datamodule,
    and the model on the meta device: no memory is allocated for its weights) without writing
    anything, so that `rotlearn-train` refuses a bad value before Hydra creates the run
    directory. Only a `ConfigError` counts: anything else the real build reports.

    Raises:
        ConfigError: naming the full key.
    """
    _instantiate(cfg, "data")
    with torch.device("meta"):
        try:
            _instantiate(cfg, "model")
        except ConfigError:
            raise
        except Exception:
            pass


def build(cfg: DictConfig) -> tuple[pl.LightningModule, pl.LightningDataModule, pl.Trainer]:
    """Model, datamodule and trainer for a composed config: `rotlearn.config.build` (validated,
    seeded; the model with its net, head, loss, optimizer and scheduler, or the auto-encoder)
    and a trainer with the configured callbacks plus the run's record keeping
    (`InterruptRecorder`, `EpochLosses`, and `RunRecords` last, with the run's HPARAMS record) and
    the guard of restored checkpoint states (`CheckpointStateGuard`), whatever `callbacks=` says,
    and rotlearn's checkpoint I/O (`RunCheckpointIO`: durable writes, bounded loads, deletes only
    the run's own checkpoints); `calibrate` adds the post-hoc calibration of the belief on the
    validation set (`rotlearn.lit.calibration.PostHocCalibration`): `auto` (the default) for a
    head with a belief, `true` always (refused by `rotlearn.config` for a head without a belief;
    an error without a validation set); `trainer.enable_model_summary` gives rotlearn's
    `ModelSummary` (in a sweep, job 0 only: once per sweep) and `trainer.enable_progress_bar` its
    `ProgressBar` (training loss and last validation error). A `TensorBoardRunLogger` is named by
    the run's overrides."""
    model, datamodule = config.build(cfg)
    runtime = _Runtime()
    callbacks = _instantiate_all(cfg, "callbacks")
    callbacks += [InterruptRecorder(), EpochLosses(), CheckpointStateGuard(cfg.paths.output_dir)]
    calibrate = OmegaConf.select(cfg, "calibrate", default="auto")
    has_belief = getattr(getattr(model, "head", None), "defines_belief", False)
    if calibrate is True or (calibrate == "auto" and has_belief):
        callbacks.append(PostHocCalibration(cfg.paths.output_dir, required=calibrate is True))
    summary = OmegaConf.select(cfg, "trainer.enable_model_summary", default=True)
    if summary and not runtime.job_num:
        callbacks.append(ModelSummary())  # Lightning's, without its column of zero FLOPs
    if OmegaConf.select(cfg, "trainer.enable_progress_bar", default=True):
        callbacks.append(ProgressBar())
    hparams = hparams_record(model.run_config, runtime.overrides, runtime.choices)
    callbacks.append(RunRecords(cfg.paths.output_dir, hparams))  # last: it reads the others
    folders = [c.dirpath for c in callbacks if isinstance(c, pl.callbacks.ModelCheckpoint)]
    plugins = OmegaConf.select(cfg, "trainer.plugins") or []
    plugins = list(plugins) if isinstance(plugins, list | ListConfig) else [plugins]
    trainer = _instantiate(
        cfg,
        "trainer",
        callbacks=callbacks,
        logger=_loggers(cfg, model.run_config, runtime) or False,
        enable_model_summary=False,  # the summary is the callback above
        plugins=[*plugins, RunCheckpointIO(cfg.paths.output_dir, folders)],  # durable, inside
    )
    return model, datamodule, trainer


class RunInterrupted(SystemExit):
    """A signal stopped the run; the exit code is the shell's 128 + signal number (SIGTERM 143,
    SIGINT 130). `status` is what `train` wrote into the run's status.json (its
    `last_finished_epoch` counted from 0, as Lightning counts; the message counts the epochs).
    Its resume command names again what a resume takes from its own command line only (`again`:
    shell words, `rundir.keys_to_give_again`: the files the run opens, the processes and devices
    its command line set); a run stopped before its first checkpoint has none (None)."""

    def __init__(
        self,
        run_dir: Path,
        signal_name: str,
        last_epoch: int | None,
        again: list[str],
        resumable: bool = True,
    ) -> None:
        self.run_dir, self.signal_name, self.last_epoch = run_dir, signal_name, last_epoch
        done = None if last_epoch is None else last_epoch + 1  # Lightning counts epochs from 0
        words = ["rotlearn-train", resume_word(run_dir.resolve()), *again]
        self.resume_command = " ".join(words) if done and resumable else None
        again_anew = "start the run again in a new folder (this one keeps the attempt's log)"
        if done:
            after = f"after {done} finished epoch{'s' * (done != 1)}"
            if self.resume_command:
                after += f"; resume: {self.resume_command}"
            else:  # no checkpoints/last.ckpt that loads (callbacks=none, a damaged one)
                after += f", but no checkpoints/last.ckpt loads to resume from: {again_anew}"
        else:
            after = "before its first epoch ended, so no checkpoint holds anything to resume: "
            after += again_anew
        self.message = f"stopped by {signal_name} {after}"
        super().__init__(128 + int(signal.Signals[signal_name]))

    @property
    def status(self) -> dict[str, Any]:
        return {
            "signal": self.signal_name,
            "last_finished_epoch": self.last_epoch,
            "resume_command": self.resume_command,
            "error": self.message,
        }


def _last_finished_epoch(run_dir: Path, trainer: pl.Trainer) -> tuple[int | None, bool]:
    """The epoch (0-based, as Lightning counts) that `<run_dir>/checkpoints/last.ckpt` ends,
    and True; where it does not load, the trainer's last finished epoch and False."""
    try:
        return int(load_checkpoint(run_dir)["epoch"]), True
    except (OSError, RuntimeError, KeyError, ValueError):
        done = trainer.fit_loop.epoch_progress.current.completed
        return (done - 1 if done else None), False


@contextlib.contextmanager
def _interruptions_recorded(trainer: pl.Trainer, run_dir: Path, cfg: DictConfig):
    """Turn a stop by SIGTERM or SIGINT (seen by the trainer's `InterruptRecorder`) into a
    status.json with status INTERRUPTED in `run_dir` and a `RunInterrupted` exit (its resume
    command from the run's config `cfg`); anything else propagates unchanged."""
    try:
        yield
    except (SystemExit, KeyboardInterrupt):
        name = getattr(find_callback(trainer, InterruptRecorder), "signal_name", None)
        if name is None:
            raise
        again = keys_to_give_again(cfg, _Runtime().overrides)
        last_epoch, resumable = _last_finished_epoch(run_dir, trainer)
        stop = RunInterrupted(run_dir, name, last_epoch, again, resumable)
        if trainer.is_global_zero:
            record_job(run_dir, "INTERRUPTED", **stop.status)
        log.warning("%s: %s", run_dir, stop.message)
        raise stop from None


@contextlib.contextmanager
def _console_lines():
    """Log records and Python warnings on lines of their own while progress bars are drawn:
    the console handlers of the root and Lightning loggers write through tqdm (which lifts the
    bars, writes the line and redraws them), and warnings go through logging meanwhile."""
    from tqdm.contrib.logging import logging_redirect_tqdm

    loggers = [logging.getLogger(), logging.getLogger("lightning.pytorch")]
    logging.captureWarnings(True)
    try:
        with logging_redirect_tqdm(loggers=loggers):
            yield
    finally:
        logging.captureWarnings(False)


def train(cfg: DictConfig) -> dict[str, Any]:
    """Fit and test the run of `cfg` in `cfg.paths.output_dir`; returns its metrics.

    The config is validated by `build`, before anything is trained; the records (metrics.json,
    timing.json, test_errors.json) are written by `RunRecords` when testing ends. A SIGTERM or
    SIGINT during `fit` or `test` stops the run at a batch boundary: `checkpoints/last.ckpt` stays
    the end of the last finished epoch, `status.json` says INTERRUPTED (signal, that epoch, the
    resume command) and `RunInterrupted` exits 143 (SIGTERM) or 130 (SIGINT).

    The process holds the run's lock while it trains (`rotlearn.locks`: a second process that
    would train the same run is refused, naming this one); other ranks of a distributed run
    share their rank 0's."""
    run_dir = Path(cfg.paths.output_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    child = is_child_rank()
    if not child:
        hold_run(run_dir)
    try:
        resume = checkpoint_to_resume(cfg, run_dir)
        torch.set_float32_matmul_precision(cfg.float32_matmul_precision)
        model, datamodule, trainer = build(cfg)
        with _console_lines(), _interruptions_recorded(trainer, run_dir, cfg):
            trainer.fit(model, datamodule=datamodule, ckpt_path=resume, weights_only=True)
            callback = trainer.checkpoint_callback
            best = callback.best_model_path if callback else ""
            ckpt_path = best if cfg.test_ckpt == "best" and best else None
            trainer.test(
                model, datamodule=datamodule, ckpt_path=ckpt_path, verbose=False, weights_only=True
            )
    finally:
        if not child:
            release_run(run_dir)
    return find_callback(trainer, RunRecords).metrics


def report(cfg: DictConfig, metrics: dict[str, Any]) -> None:
    """Log a finished run's test errors, its directory (and what it wrote there) and how to open
    TensorBoard on it, if it logged to TensorBoard."""
    run_dir = Path(cfg.paths.output_dir)
    try:
        shown = run_dir.resolve().relative_to(Path.cwd())
    except ValueError:
        shown = run_dir
    weights = f"{metrics.get('tested_weights')} weights"
    if metrics.get("tested_epochs") != metrics.get("epochs"):  # test_ckpt=best, an earlier one
        weights += f" of epoch {metrics.get('tested_epochs')}/{metrics.get('epochs')}"
    if metrics.get("task") == "autoencoder":
        log.info(
            "test reconstruction error (auto-encoder, %s): mean L1 %.4f",
            weights,
            metrics.get("test/recon_mean", math.nan),
        )
    else:
        log.info(
            "test error (%s head, %s): mean %.3f deg, median %.3f deg, p90 %.3f deg",
            metrics.get("rep"),
            weights,
            metrics.get("test/err_mean", math.nan),
            metrics.get("test/err_median", math.nan),
            metrics.get("test/err_p90", math.nan),
        )
        log.info(
            'baseline "predict identity": mean %.3f deg, median %.3f deg',
            metrics.get("test/identity_err_mean", math.nan),
            metrics.get("test/identity_err_median", math.nan),
        )
    records = ["metrics.json", "checkpoints/", "tensorboard/", "csv/"]  # what the run wrote
    written = [r for r in records if run_dir.joinpath(r.rstrip("/")).exists()]
    log.info("run directory: %s (%s)", shown, ", ".join(written))
    if command := tensorboard_command(run_dir):  # none for logger=csv or logger=none
        log.info("open TensorBoard: %s", command)
