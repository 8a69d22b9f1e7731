"""`rotlearn-train` (also `python -m rotlearn.train`): train, test, write the run's metrics.json.

Every component comes from the Hydra config with `hydra.utils.instantiate`; every file goes below
`paths.output_dir` (Hydra's run directory). See conf/train.yaml.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
import warnings
from pathlib import Path
from typing import Any

import hydra
import lightning.pytorch as pl
import torch
from hydra.errors import InstantiationException
from lightning.pytorch.loggers import TensorBoardLogger
from omegaconf import DictConfig, OmegaConf

from rotlearn.checkpoint import resolve_checkpoint
from rotlearn.cli.replay import saved_overrides
from rotlearn.cli.schemas import ConfigError, validate
from rotlearn.errors import ConfigValueError
from rotlearn.io import write_json_atomic
from rotlearn.lit import AutoEncoderModule, EpochTimer, RotationRegressor
from rotlearn.nets import ConvAutoEncoder
from rotlearn.paths import config_dir
from rotlearn.trust import UntrustedConfigError

__all__ = ["ConfigError", "build", "main", "resume_arguments", "train"]

log = logging.getLogger("rotlearn")

# Lightning's advice that does not apply: batches are drawn on the device (no loader workers),
# and scalars are logged once per epoch on purpose.
for _pattern in (".*does not have many workers.*", ".*smaller than the logging interval.*"):
    warnings.filterwarnings("ignore", _pattern)


def _instantiate(cfg: DictConfig, key: str, **kwargs: Any) -> Any:
    """Instantiate the config node `key`, turning a component's complaint into a `ConfigError`."""
    node = OmegaConf.select(cfg, key)
    if node is None:
        raise ConfigError(f"config key {key} is missing")
    try:
        return hydra.utils.instantiate(node, **kwargs)
    except InstantiationException as exc:
        cause = exc.__cause__
        while cause is not None and not isinstance(cause, ConfigValueError):
            cause = cause.__cause__
        if cause is None:
            raise
        raise ConfigError(f"config key {key}.{cause.key}: {cause.message}") from exc


def _instantiate_all(cfg: DictConfig, key: str) -> list[Any]:
    node = OmegaConf.select(cfg, key) or {}
    return [_instantiate(cfg, f"{key}.{name}") for name in node]


def build(
    cfg: DictConfig,
) -> tuple[RotationRegressor | AutoEncoderModule, pl.LightningDataModule, pl.Trainer]:
    """Model, datamodule and trainer for a composed config (validated, seeds set first).

    `task=rotation` builds a `RotationRegressor`; `task=autoencoder` an `AutoEncoderModule`
    (spec section 8: no head, no loss), whose net must be `net=autoencoder`."""
    validate(cfg)
    task = cfg.get("task", "rotation")
    if task not in ("rotation", "autoencoder"):
        raise ConfigError(f"config key task: must be 'rotation' or 'autoencoder', got {task!r}")
    pl.seed_everything(cfg.seed, workers=True, verbose=False)
    datamodule = _instantiate(cfg, "data")
    head = _instantiate(cfg, "rep") if task == "rotation" else None
    net = _instantiate(cfg, "net")
    if isinstance(net, ConvAutoEncoder) != (task == "autoencoder"):
        raise ConfigError(
            f"config key task: task={task} cannot train net {cfg.net._target_} "
            "(task=autoencoder goes with net=autoencoder, every other net with task=rotation)"
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
    trainer = _instantiate(
        cfg,
        "trainer",
        callbacks=_instantiate_all(cfg, "callbacks"),
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


def train(cfg: DictConfig) -> dict[str, Any]:
    """Fit, test and write `metrics.json` in `cfg.paths.output_dir`; returns those metrics.

    The config is validated by `build`, before anything is trained."""
    run_dir = Path(cfg.paths.output_dir)
    resume = cfg.get("ckpt_path")
    if (run_dir / "metrics.json").exists():
        raise FileExistsError(
            f"{run_dir} holds a finished run (metrics.json); it is never rewritten"
        )
    if resume:
        resume = str(resolve_checkpoint(resume))
        log.info("resuming from %s", resume)
    elif (run_dir / "checkpoints").exists():
        raise FileExistsError(
            f"{run_dir} already holds a run; rotlearn never overwrites one (to continue it: "
            f"ckpt_path={run_dir})"
        )
    torch.set_float32_matmul_precision(cfg.float32_matmul_precision)
    model, datamodule, trainer = build(cfg)

    trainer.fit(model, datamodule=datamodule, ckpt_path=resume or None, weights_only=True)
    metrics = _scalars(trainer.callback_metrics)
    best_path = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
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


def _newest_run(root: Path) -> Path:
    runs = sorted(p.parent.parent for p in root.glob("*/checkpoints/last.ckpt"))
    if not runs:
        raise SystemExit(f"rotlearn-train: ckpt_path=last, but no run under {root} has a last.ckpt")
    return runs[-1]  # run directories are named by their start time


def resume_arguments(argv: list[str], runs_root: Path = Path("outputs/runs")) -> list[str]:
    """Rewrite a command line with `ckpt_path=...` so that Hydra continues that run in its own
    directory with its own overrides: `[saved overrides, new overrides, ckpt_path=<file>,
    hydra.run.dir=<run dir>]`. Other command lines are returned unchanged."""
    values = [a.split("=", 1)[1] for a in argv if a.startswith("ckpt_path=")]
    if not values or values[-1] in ("", "null", "None"):
        return argv
    if "-m" in argv or "--multirun" in argv:
        raise SystemExit("rotlearn-train: ckpt_path resumes one run; it cannot be used with -m")
    if values[-1] == "last":
        ckpt = resolve_checkpoint(_newest_run(runs_root))
    else:
        try:
            ckpt = resolve_checkpoint(values[-1])
        except FileNotFoundError as exc:
            raise SystemExit(f"rotlearn-train: ckpt_path: {exc}") from None
    run_dir = ckpt.parent.parent if ckpt.parent.name == "checkpoints" else ckpt.parent
    try:  # the run directory is untrusted data: its overrides are checked before Hydra starts
        previous = [o for o in saved_overrides(run_dir) if not o.startswith("ckpt_path=")]
    except (FileNotFoundError, UntrustedConfigError) as exc:
        raise SystemExit(f"rotlearn-train: ckpt_path: {exc}") from None
    new = [a for a in argv if not a.startswith("ckpt_path=")]
    return [
        *previous,
        *new,
        f"ckpt_path={ckpt.resolve()}",
        f"hydra.run.dir={run_dir.resolve()}",
    ]


@hydra.main(version_base="1.3", config_path=str(config_dir()), config_name="train")
def _hydra_main(cfg: DictConfig) -> float:
    metrics = train(cfg)
    _report(cfg, metrics)
    # what sweepers (Optuna) minimise: the validation median error, never a test number
    return metrics.get("val/err_median", metrics.get("val/loss", math.nan))


def main() -> float:
    """Entry point of `rotlearn-train`; returns the validation median error (for sweepers)."""
    sys.argv[1:] = resume_arguments(sys.argv[1:])
    return _hydra_main()


if __name__ == "__main__":
    main()
