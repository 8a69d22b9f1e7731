"""`rotlearn-eval ckpt=<run>`: test a trained checkpoint again, with the OOD evaluation;
`rotlearn-eval ckpt=[<run>,<run>,...]`: test the ensemble of several (`rotlearn.heads.
EnsembleHead`: the product of the members' beliefs), its calibration fitted on the validation
set first (the members' own temperatures are applied inside it).

The run's own config (saved in the checkpoint) rebuilds the data, net and head; the non-null keys
of conf/eval.yaml's `ood`, `data` and `trainer` are merged into it. Results go to a new directory
(`outputs/eval/<time>`): metrics.json, ood.csv, ood.md, TensorBoard events and evaluated.yaml (the
run config it evaluated, by which `rotlearn-report` puts it beside the runs). Nothing in the
trained run's directory is touched. The belief's calibration fitted for the checkpoint
(`calibrate` in training: `checkpoints/temperature.json`, its temperature and level map) is
applied (`temperature` in metrics.json); it is never refitted here.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import hydra
from omegaconf import DictConfig, ListConfig, OmegaConf

from rotlearn.errors import ConfigError
from rotlearn.paths import EVALUATED_FILE, checkpoint_file, config_dir

if TYPE_CHECKING:
    from rotlearn.checkpoint import SavedRun

__all__ = ["evaluate", "evaluation_config", "main", "usage"]

log = logging.getLogger("rotlearn")

DEFAULT_OOD = config_dir() / "callbacks" / "ood.yaml"
# What the evaluation keeps of the trained run's trainer config: how it computes, not where it
# writes (outputs go to the evaluation's own directory) nor on what (the devices are the
# evaluation's command line's: trainer.accelerator, trainer.devices; default auto and one).
SAVED_TRAINER_KEYS = ("_target_", "precision", "deterministic")
DEFAULT_DEVICES = {"accelerator": "auto", "devices": 1}


def _set(node: DictConfig | None) -> dict[str, Any]:
    return {
        k: v for k, v in OmegaConf.to_container(node or {}, resolve=True).items() if v is not None
    }


def _run_ood(callbacks: Any) -> Any:
    """A run's OOD callback node (`callbacks.ood`), else conf/callbacks/ood.yaml's (a run
    trained without it), with its `autoencoder_ckpt` null: a path outside the run, which an
    evaluation never opens (its own command line's `ood.autoencoder_ckpt=` is used). Null, not
    dropped: a report of the run and its evaluation would tell them apart by the key alone."""
    ood = callbacks.get("ood") if isinstance(callbacks, Mapping) else None
    ood = OmegaConf.load(DEFAULT_OOD).ood if ood is None else ood
    ood = OmegaConf.to_container(ood) if isinstance(ood, DictConfig) else ood
    return {**ood, "autoencoder_ckpt": None} if isinstance(ood, dict) else ood


def evaluation_config(cfg: DictConfig, saved: SavedRun) -> DictConfig:
    """The saved run config (already checked: `rotlearn.checkpoint.load_run`) with the
    evaluation's overrides, OOD callback and output paths. Of the saved trainer config only the
    keys in `SAVED_TRAINER_KEYS` are kept; the devices and the rest come from the evaluation's
    own command line, as `data.num_workers` does (a checkpoint never chooses how many processes
    are launched: a received one said 64 loader workers, and eval ran 317 processes)."""
    if saved.task == "autoencoder":
        use = f"it scores a head run's test pairs with ood.autoencoder_ckpt={cfg.ckpt}"
        raise ConfigError("ckpt", f"{cfg.ckpt} is an auto-encoder, not a rotation model: {use}")
    if saved.task != "rotation":
        raise ConfigError("ckpt", f"{cfg.ckpt}: a {saved.task} checkpoint, not a rotation model")
    run = OmegaConf.create(OmegaConf.to_container(saved.config))
    if cfg.expect_rep is not None and cfg.expect_rep != run.rep.name:
        raise ConfigError(
            "ckpt",
            f"{cfg.ckpt} was trained with rep={run.rep.name}, not expect_rep={cfg.expect_rep}",
        )
    out = cfg.paths.output_dir
    run.callbacks = {"ood": OmegaConf.merge(_run_ood(run.get("callbacks")), _set(cfg.ood))}
    run.data.pop("cache_dir", None)  # caches go where this command line says, or under data.root
    run.data.pop("num_workers", None)  # loader processes: this command line's, or the default
    run.data = OmegaConf.merge(run.data, _set(cfg.data))
    trainer = {k: v for k, v in run.trainer.items() if k in SAVED_TRAINER_KEYS}
    trainer["_target_"] = "lightning.pytorch.Trainer"
    run.trainer = OmegaConf.merge(  # no checkpointing: nothing is trained, nothing is saved
        trainer, DEFAULT_DEVICES, _set(cfg.trainer), {"default_root_dir": out},
        {"enable_checkpointing": False},
    )  # fmt: skip
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


def evaluated_config(cfg: DictConfig, saved: SavedRun, members: int) -> DictConfig:
    """What an evaluation evaluated, as a run config (`EVALUATED_FILE`, which `rotlearn-report`
    reads in place of the evaluation's own): the trained run's config as its run directory
    keeps it (`.hydra/config.yaml`, read bounded, never resolved, so that it compares key by key
    with the runs' own; the checkpoint's resolved copy where the run has none; an ensemble's:
    its first member's), with the evaluation's data and OOD keys merged in, and
    `evaluated.members`, the number of runs whose ensemble was tested (1: one run). So an
    evaluation sits in a report beside the runs it evaluated, told apart by what it changed."""
    from rotlearn.report.runs import read_yaml, run_choices

    base: Any = None
    choices: dict[str, str] = {}
    if saved.path.parent.name == "checkpoints":  # a run directory's checkpoint: its files
        run_dir = saved.path.parent.parent
        base = read_yaml(run_dir / ".hydra" / "config.yaml")
        choices = run_choices(run_dir, [])  # the run's config group options (rep: a, ...)
    if not isinstance(base, dict) or not all(isinstance(k, str) for k in base):
        base = OmegaConf.to_container(saved.config)
    base["hydra"] = {"runtime": {"choices": choices}}  # where Hydra keeps them; no setting
    callbacks = base.get("callbacks") if isinstance(base.get("callbacks"), dict) else {}
    base["callbacks"] = {**callbacks, "ood": _run_ood(callbacks)}
    changed = {"data": _set(cfg.data), "callbacks": {"ood": _set(cfg.ood)}}
    try:
        return OmegaConf.merge(base, changed, {"evaluated": {"members": members}})
    except Exception:  # a file OmegaConf cannot hold: the checkpoint's own copy
        own = OmegaConf.to_container(saved.config)
        return OmegaConf.merge(own, changed, {"evaluated": {"members": members}})


@contextlib.contextmanager
def _refused_on_ckpt(cfg: DictConfig) -> Iterator[None]:
    """What a reader of `cfg.ckpt` refuses (no such file, an unsafe file, an untrusted config,
    another task) as a `ConfigError` on `ckpt`, naming it."""
    try:
        yield
    except (FileNotFoundError, ValueError) as exc:
        raise ConfigError("ckpt", f"{cfg.ckpt}: {exc}") from None


def _saved_run(cfg: DictConfig) -> SavedRun:
    """The run `cfg.ckpt` names, read through the one loader (`rotlearn.checkpoint.load_run`)."""
    from rotlearn.checkpoint import load_run

    with _refused_on_ckpt(cfg):
        return load_run(cfg.ckpt)


def _ensemble(paths: list[str]) -> tuple[Any, Any, SavedRun]:
    """The ensemble of the runs `paths` (`rotlearn.inference.ensemble_members`: runs with a
    belief) and the first member's run, whose data the evaluation reads; every member must have
    been trained on the same kind of input: the same datamodule and the same values of what its
    `input_keys` name (frame size, channels, normalisation).

    Raises:
        ConfigError: on `ckpt`, naming the member and what it cannot be used for.
    """
    from rotlearn.config.source import class_attribute
    from rotlearn.inference import ensemble_members

    try:
        net, head, runs = ensemble_members(paths)
    except (FileNotFoundError, ValueError) as exc:  # unsafe file, untrusted config, ...
        raise ConfigError("ckpt", str(exc)) from None
    data = [OmegaConf.select(run.config, "data") for run in runs]
    data = [node if isinstance(node, DictConfig) else {} for node in data]  # none: no keys
    wanted = class_attribute(str(data[0].get("_target_")), "input_keys")
    keys = ("_target_", *(wanted if isinstance(wanted, list) else ()))
    for run, node in zip(runs[1:], data[1:], strict=True):
        for key in (k for k in keys if node.get(k) != data[0].get(k)):
            raise ConfigError(
                "ckpt",
                f"{run.path} was trained with data.{key}={node.get(key)!r}, {runs[0].path} "
                f"with {data[0].get(key)!r}; an ensemble's members must take the same input",
            )
    return net, head, runs[0]


def evaluate(cfg: DictConfig) -> dict[str, Any]:
    """Test the checkpoint `cfg.ckpt` (or the ensemble of a list of them) with the OOD callback;
    returns what the run's records (`rotlearn.lit.RunRecords`) wrote to metrics.json."""
    from rotlearn.cli.rundir import files_to_open
    from rotlearn.cli.train import build
    from rotlearn.io import write_text_atomic
    from rotlearn.lit import RunRecords, find_callback

    paths = list(cfg.ckpt) if isinstance(cfg.ckpt, ListConfig) else None
    if paths is None:
        saved = _saved_run(cfg)
    else:
        net, head, saved = _ensemble(paths)
    ckpt = saved.path
    run = evaluation_config(cfg, saved)
    for key, named in files_to_open(saved.config).items():  # rundir.FILE_KEYS
        log.warning("%s: the run's %s (%s) is not opened (a file never names another to read); "
                    "for the autoencoder score: ood.autoencoder_ckpt=<its run>", cfg.ckpt, key,
                    named)  # fmt: skip
    try:  # the weights against the model the config describes, built on the meta device first
        saved.check_fits("model", prefix="")
    except ValueError as exc:
        raise ConfigError("ckpt", str(exc)) from None
    if paths is not None:
        run.calibrate = True  # the ensemble's own temperature and level map, on validation
    model, datamodule, trainer = build(run)
    if paths is None:
        model.load_state_dict(saved.state_dict)
        model.belief_temperature = saved.temperature  # the test metrics and OOD scores use it
        model.belief_levels = saved.level_map
    else:
        model.net, model.head = net, head
    write_text_atomic(
        Path(cfg.paths.output_dir) / EVALUATED_FILE,
        OmegaConf.to_yaml(evaluated_config(cfg, saved, len(paths) if paths else 1)),
    )
    records = find_callback(trainer, RunRecords)
    records.facts = {"ckpt": str(ckpt.resolve()), "rep": run.rep.name}
    if paths is not None:
        records.facts |= {"members": [str(Path(p).resolve()) for p in paths], "rep": "ensemble"}
    trainer.test(model, datamodule=datamodule, verbose=False)  # writes metrics.json, once
    return records.metrics


@hydra.main(version_base="1.3", config_path=str(config_dir()), config_name="eval")
def _hydra_main(cfg: DictConfig) -> float:
    from rotlearn.cli.callbacks import end_failed_job

    try:
        metrics = evaluate(cfg)
    except (OSError, ValueError, ArithmeticError) as exc:  # the input's or the machine's fault
        end_failed_job(cfg.paths.output_dir, exc, "rotlearn-eval")  # a bug keeps its traceback
        log.error("rotlearn-eval: %s", exc)
        raise
    log.info(
        "test error (%s head): mean %.3f deg, median %.3f deg; OOD tables in %s",
        metrics["rep"], metrics.get("test/err_mean", math.nan),
        metrics.get("test/err_median", math.nan), Path(cfg.paths.output_dir) / "ood.md",
    )  # fmt: skip
    return metrics.get("test/err_median", math.nan)


def usage(root: Path | None = None) -> str:
    """The `--help` text: what conf/eval.yaml says it takes (its comments and keys). Reads the
    file only."""
    text = (Path(root or config_dir()) / "eval.yaml").read_text()
    head, _, body = text.partition("defaults:")
    keys = body[body.index("ckpt:") : body.index("\npaths:")]
    lines = [
        "rotlearn-eval: test a trained image-pair run (data=kitti, mav) again, with the OOD "
        "evaluation, without retraining (a synthetic run's model: rotlearn-predict).",
        "",
        "usage: rotlearn-eval ckpt=<run dir or .ckpt, or a list of them> [key=value ...] [-m]",
        *(line.removeprefix("# ") for line in head.strip().splitlines()[1:]),
        "",
        "keys (conf/eval.yaml; null keeps the run's own value):",
        *(f"  {line}" for line in keys.rstrip().splitlines()),
        "",
        "sweep=ood_quantile (with -m): one evaluation per OOD quantile",
        "outputs: outputs/eval/<time>/ (metrics.json, ood.csv, ood.md, tensorboard/,",
        "  evaluated.yaml: the run config it evaluated)",
        "rotlearn-report <runs> <evaluations>: evaluations beside the runs (evaluated.members=K)",
        "rotlearn-eval --hydra-help: Hydra's own flags",
    ]
    return "\n".join(lines) + "\n"


def _targets(tree: Any):
    """Every `_target_` value in plain data."""
    if isinstance(tree, dict):
        if "_target_" in tree:
            yield tree["_target_"]
        tree = list(tree.values())
    for item in tree if isinstance(tree, list) else ():
        yield from _targets(item)


def _first_look(cfg: DictConfig) -> None:
    """Refuse what the files alone tell (`rotlearn.config.checks.check_keys`: e.g. OOD callbacks
    on data that is not image pairs, a data folder that is not there) before torch and the
    components load. The checkpoint's config is read without torch and without unpickling
    (`rotlearn.checkpoint.saved_config`); it is looked at only where every `_target_`
    is an allowlisted library class or a rotlearn component (its source marks it
    `@config_target`), and nothing is built or imported from it; `load_run` then checks it in
    full (the allowlist by import). A file that `load_run` would refuse unread (no whole archive,
    a pickle past the bounds) is refused here, as `load_run` would say it. Anything else is left
    to those checks."""
    from types import SimpleNamespace

    from rotlearn.checkpoint import rebuildable, saved_config, tested_checkpoint
    from rotlearn.config.checks import check_keys, plain
    from rotlearn.config.source import class_attribute, is_marked
    from rotlearn.trust import LIBRARY_TARGETS

    try:  # what load_run would refuse of the file (a pickle past the bounds) is said here
        with _refused_on_ckpt(cfg):
            saved = rebuildable(saved_config(tested_checkpoint(cfg.ckpt)))
    except OSError:
        return  # load_run says why
    try:  # a deep, odd or foreign config is left to load_run (RecursionError, TypeError, ...)
        named = [str(t) for t in _targets(saved) if t not in LIBRARY_TARGETS]
        if "${" in repr(saved) or not all(
            t.startswith("rotlearn.") and is_marked(t) for t in named
        ):
            return
        model = saved.get("model") or {}
        task = class_attribute(str(model["_target_"]), "task") if "_target_" in model else None
        task = task or saved.get("task", "rotation")
        values = plain(
            evaluation_config(cfg, SimpleNamespace(config=OmegaConf.create(saved), task=task))
        )
    except ConfigError:
        raise
    except Exception:
        return
    check_keys(values)


def _ckpt_values(value: str, multirun: bool) -> tuple[list[str], bool]:
    """The checkpoint paths a `ckpt=` value names and whether they make one ensemble: one path,
    Hydra's list `[<run>,<run>,...]` (an ensemble) or, with -m, a sweep `<run>,<run>` (one
    evaluation each), parsed by Hydra's own override grammar, so quoting works as on the
    command line."""
    if not value.strip():
        raise SystemExit("rotlearn-eval: ckpt is empty; pass a run directory or a .ckpt file")
    if not value.lstrip().startswith("[") and "," not in value:
        return [value], False
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    what = "a list of runs" if value.lstrip().startswith("[") else "a run or a sweep of runs"
    try:
        override = OverridesParser.create().parse_override(f"ckpt={value}")
    except HydraException as exc:  # the grammar's own (no viable alternative ...), one line
        from rotlearn.config import grammar_reason

        why = grammar_reason(exc, f"ckpt={value}")
        raise SystemExit(f"rotlearn-eval: ckpt: {value} is not {what} ({why})") from None
    if override.is_sweep_override():
        if not multirun:
            raise SystemExit(
                f"rotlearn-eval: ckpt: {value} is a sweep: add -m for one evaluation per run, "
                f"or write ckpt=[{value}] for their ensemble"
            )
        swept = [v if isinstance(v, list) else [v] for v in override.sweep_iterator()]
        return [str(path) for paths in swept for path in paths], False  # each job its own
    parsed = override.value()
    if isinstance(parsed, list):
        if not parsed:
            raise SystemExit(f"rotlearn-eval: ckpt: {value} is not a list of runs")
        return [str(v) for v in parsed], True
    return [str(parsed)], False


def _checked(argv: list[str]) -> list[str]:
    """Refuse, before Hydra makes the evaluation's directory, a command line that cannot work
    (SystemExit naming the key; nothing is written): no ckpt, a ckpt that is not a run (a sweep
    directory: its jobs listed), an evaluation or sweep directory that exists and is not empty,
    and a run config that does not validate with the evaluation's settings (e.g. OOD callbacks
    on data that is not image pairs, a data folder that is not there; an ensemble's: its first
    member's; with -m, the first job's); for an ensemble, a member without a belief or trained
    on other input (`_ensemble`).
    Returns the arguments for Hydra (`+` before a data key that eval.yaml does not list)."""
    from rotlearn.config import command_line_config, validate

    if any(a.startswith("-") and a not in ("-m", "--multirun") for a in argv):
        return argv  # Hydra's own flags (--cfg, --hydra-help, ...)
    values = [a.split("=", 1)[1] for a in argv if a.startswith("ckpt=")]
    if not values:
        raise SystemExit("rotlearn-eval: ckpt=<run directory or .ckpt file> is missing (--help)")
    from rotlearn.cli.rundir import is_child_rank, refuse_an_existing_output_dir, runs_a_sweep

    _refuse_keys_eval_does_not_take(argv)
    multirun = runs_a_sweep(argv)  # each job is checked as it runs
    members, ensemble = _ckpt_values(values[-1], multirun)
    try:
        for member in members:
            checkpoint_file(member)
    except FileNotFoundError as exc:
        raise SystemExit(f"rotlearn-eval: ckpt: {exc} (nothing was written)") from None
    try:
        first = _ensemble(members)[2] if ensemble and not multirun else None
        cfg, args = command_line_config(argv, "new-eval", config_name="eval")  # -m: first job's
        if not is_child_rank():  # the directory of the arguments Hydra runs (with their `+`)
            refuse_an_existing_output_dir(cfg, args, "eval", "rotlearn-eval")
        if first is not None:  # an ensemble reads its first member's data (`_ensemble`)
            validate(evaluation_config(cfg, first))
        elif isinstance(cfg.ckpt, str):  # one run (with -m, the first job's; an ensemble
            _first_look(cfg)  # among swept values is checked by its own job)
            validate(evaluation_config(cfg, _saved_run(cfg)))
    except ConfigError as exc:
        if exc.key == _OOD_NODE[:-1]:  # its needs: the run's data has no OOD evaluation
            exc = ConfigError("ckpt", f"{cfg.ckpt} is no image-pair run: rotlearn-eval tests a "
                              f"run again with the OOD evaluation, which {exc.message}; to use "
                              "its model: rotlearn-predict or rotlearn.load")  # fmt: skip
        elif exc.key.startswith(_OOD_NODE):  # the run's OOD callback: set as ood.<key> here
            exc = ConfigError(_as_typed(exc.key), _as_typed(exc.message))
        raise SystemExit(f"rotlearn-eval: {exc} (nothing was written)") from None
    return args


_OOD_NODE = "callbacks.ood."  # where eval.yaml's `ood` keys are merged (`evaluation_config`)


def _as_typed(text: str) -> str:
    """`text` with the OOD callback's keys as rotlearn-eval takes them: `ood.<key>`."""
    return text.replace(_OOD_NODE, "ood.")


def _refuse_keys_eval_does_not_take(argv: list[str]) -> None:
    """SystemExit for an override whose top-level key conf/eval.yaml has not (with or without
    `+`, which Hydra would append and the evaluation ignore): `callbacks.ood.quantiles`, the
    run's own key, is set here as `ood.quantiles`."""
    from rotlearn.config.checks import refuse_unknown
    from rotlearn.report.identity import is_hydra_key

    config = OmegaConf.load(config_dir() / "eval.yaml")
    groups = [str(k).split("@")[0] for d in config.get("defaults", []) if isinstance(d, Mapping)
              for k in d]  # fmt: skip
    allowed = sorted({*map(str, config), *groups} - {"defaults", "_self_"})
    keys = [a.lstrip("+~").split("=", 1)[0] for a in argv if not a.startswith("-")]
    tops = [k.split(".", 1)[0] for k in keys if not is_hydra_key(k)]
    near = next(
        (f"; {_as_typed(k)} sets the run's {k}" for k in keys if k.startswith(_OOD_NODE)), ""
    )
    try:
        refuse_unknown("", tops, allowed, near)
    except ConfigError as exc:
        raise SystemExit(f"rotlearn-eval: {exc} (nothing was written)") from None


def main() -> float | None:
    """Entry point of `rotlearn-eval`; None after `--help`. A new evaluation never writes into an
    existing, non-empty directory (`_checked`)."""
    argv = sys.argv[1:]
    if any(a in ("-h", "--help") for a in argv):
        print(usage(), end="")
        return None
    from rotlearn.cli import refusals_exit_at_once

    with refusals_exit_at_once():
        sys.argv[1:] = _checked(argv)
    return _hydra_main()


if __name__ == "__main__":
    main()
