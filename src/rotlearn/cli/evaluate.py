"""`rotlearn-eval ckpt=<run>`: test a trained checkpoint again, with the OOD evaluation.

The run's own config (saved in the checkpoint) rebuilds the data, net and head; the non-null keys
of conf/eval.yaml's `ood`, `data` and `trainer` are merged into it. Results go to a new directory
(`outputs/eval/<time>`): metrics.json, ood.csv, ood.md and TensorBoard events. Nothing in the
trained run's directory is touched. The belief's temperature fitted for the checkpoint
(`calibrate=true` in training: `checkpoints/temperature.json`) is applied (`temperature` in
metrics.json); it is never refitted here.
"""

from __future__ import annotations

import logging
import math
import sys
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from rotlearn.checkpoint import SavedRun, load_run
from rotlearn.errors import ConfigError
from rotlearn.io import write_json_atomic
from rotlearn.paths import config_dir

__all__ = ["evaluate", "evaluation_config", "main"]

log = logging.getLogger("rotlearn")

DEFAULT_OOD = config_dir() / "callbacks" / "ood.yaml"
# What the evaluation keeps of the trained run's trainer config (how it computes, not where it
# writes: outputs go to the evaluation's own directory).
SAVED_TRAINER_KEYS = ("_target_", "accelerator", "devices", "precision", "deterministic")


def _set(node: DictConfig | None) -> dict[str, Any]:
    return {
        k: v for k, v in OmegaConf.to_container(node or {}, resolve=True).items() if v is not None
    }


def evaluation_config(cfg: DictConfig, saved: SavedRun) -> DictConfig:
    """The saved run config (already checked: `rotlearn.checkpoint.load_run`) with the
    evaluation's overrides, OOD callback and output paths. Of the saved trainer config only the
    keys in `SAVED_TRAINER_KEYS` are kept; the rest comes from the evaluation's own command line."""
    if saved.task != "rotation":
        raise ConfigError("ckpt", f"{cfg.ckpt}: a {saved.task} checkpoint, not a rotation model")
    run = OmegaConf.create(OmegaConf.to_container(saved.config))
    if cfg.expect_rep is not None and cfg.expect_rep != run.rep.name:
        raise ConfigError(
            "ckpt",
            f"{cfg.ckpt} was trained with rep={run.rep.name}, not expect_rep={cfg.expect_rep}",
        )
    out = cfg.paths.output_dir
    ood = OmegaConf.select(run, "callbacks.ood")
    if ood is None:
        ood = OmegaConf.load(DEFAULT_OOD).ood
    run.callbacks = {"ood": OmegaConf.merge(ood, _set(cfg.ood))}
    run.data.pop("cache_dir", None)  # caches go where this command line says, or under data.root
    run.data = OmegaConf.merge(run.data, _set(cfg.data))
    trainer = {k: v for k, v in run.trainer.items() if k in SAVED_TRAINER_KEYS}
    run.trainer = OmegaConf.merge(trainer, _set(cfg.trainer), {"default_root_dir": out})
    run.logger = {
        "tensorboard": {
            "_target_": "rotlearn.lit.TensorBoardRunLogger",
            "save_dir": out, "name": "tensorboard", "version": None, "default_hp_metric": False,
        }
    }  # fmt: skip
    run.paths = {"output_dir": out}
    run.ckpt_path = None
    run.calibrate = False  # the checkpoint's own temperature is applied (`evaluate`), not refitted
    return run


def evaluate(cfg: DictConfig) -> dict[str, Any]:
    """Test the checkpoint `cfg.ckpt` with the OOD callback; writes metrics.json; returns it."""
    from rotlearn.cli.train import build

    try:
        saved = load_run(cfg.ckpt)
    except (FileNotFoundError, ValueError) as exc:  # unsafe file, untrusted config, other task
        raise ConfigError("ckpt", f"{cfg.ckpt}: {exc}") from None
    ckpt = saved.path
    run = evaluation_config(cfg, saved)
    model, datamodule, trainer = build(run)
    model.load_state_dict(saved.state_dict)
    model.belief_temperature = saved.temperature  # the test metrics and OOD scores use it
    trainer.test(model, datamodule=datamodule, verbose=False)
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1}
    metrics.update(
        {"ckpt": str(ckpt.resolve()), "rep": run.rep.name, "temperature": saved.temperature}
    )
    write_json_atomic(Path(cfg.paths.output_dir) / "metrics.json", metrics)
    return metrics


@hydra.main(version_base="1.3", config_path=str(config_dir()), config_name="eval")
def _hydra_main(cfg: DictConfig) -> float:
    try:
        metrics = evaluate(cfg)
    except ConfigError as exc:
        log.error("rotlearn-eval: %s", exc)
        raise
    log.info(
        "test error (%s head): mean %.3f deg, median %.3f deg; OOD tables in %s",
        metrics["rep"], metrics.get("test/err_mean", math.nan),
        metrics.get("test/err_median", math.nan), Path(cfg.paths.output_dir) / "ood.md",
    )  # fmt: skip
    return metrics.get("test/err_median", math.nan)


def main() -> float:
    """Entry point of `rotlearn-eval`."""
    return _hydra_main()


if __name__ == "__main__":
    sys.exit(main() is None)
