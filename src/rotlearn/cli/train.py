"""`rotlearn-train` (also `python -m rotlearn.train`): train and test one run (or a sweep, -m).

The entry point only. `rotlearn-train --help` is answered from the config directory alone, without
importing torch or Lightning (a second instead of several); a command line with an unknown option
or key, or missing data, is refused as fast (`rotlearn.config` reads the components' source, not
their modules); everything else is validated, then the Hydra app starts, which trains with
`rotlearn.cli.training` (`build`, `train`, `RunInterrupted`, `ConfigError`: importable from here
too, loaded on first use). See conf/train.yaml.
"""

from __future__ import annotations

import math
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import hydra
from omegaconf import DictConfig

from rotlearn.paths import config_dir

if TYPE_CHECKING:
    from rotlearn.cli.training import ConfigError, RunInterrupted, build, train

__all__ = ["ConfigError", "RunInterrupted", "build", "main", "train", "usage"]

_FROM_TRAINING = ("ConfigError", "RunInterrupted", "build", "train")
HELP_FLAGS = ("-h", "--help")


def __getattr__(name: str) -> Any:  # PEP 562: the training stack is imported on first use
    if name in _FROM_TRAINING:
        from rotlearn.cli import training

        return getattr(training, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _options(group_dir: Path) -> str:
    return ", ".join(sorted(p.stem for p in group_dir.glob("*.yaml")))


def usage(root: Path | None = None) -> str:
    """The `--help` text: the config groups and their options (conf/<group>/*.yaml), the top-level
    keys of conf/train.yaml with their comments, and where to see more. Reads files only."""
    root = Path(root or config_dir())
    groups = sorted(
        d for d in root.rglob("*") if d.is_dir() and d.relative_to(root).parts[0] != "hydra"
    )
    width = max(len(str(d.relative_to(root))) for d in groups)
    lines = [
        "rotlearn-train: train and test one run, or a sweep with -m (a Hydra app).",
        "",
        "usage: rotlearn-train [group=option ...] [key=value ...] [-m]",
        "  e.g. rotlearn-train rep=sixd data=synthetic optim.lr=1e-3 trainer.max_epochs=10",
        "",
        f"config groups (group=option; files in {root}):",
    ]
    lines += [f"  {d.relative_to(root)!s:<{width}}  {_options(d)}" for d in groups]
    lines += ["", "top-level keys (conf/train.yaml):"]
    text = (root / "train.yaml").read_text()
    shown = False  # the last top-level key was shown: its comment's next lines are too
    for line in text.splitlines():
        match = re.match(r"^(\w+):\s*(\S.*)$", line)
        if match or not re.match(r"^\s+#", line):
            shown = bool(match) and match.group(1) not in ("defaults", "hydra", "paths")
        if shown:
            lines.append(f"  {line}")
    lines += [
        "",
        "more:",
        "  rotlearn-train [overrides] --cfg job  the composed config: every key and its value",
        "  rotlearn-train ckpt_path=last         resume the newest interrupted run",
        "  rotlearn-train --hydra-help           Hydra's own flags (--multirun, --cfg, --info)",
    ]
    return "\n".join(lines) + "\n"


@hydra.main(version_base="1.3", config_path=str(config_dir()), config_name="train")
def _hydra_main(cfg: DictConfig) -> float:
    from rotlearn.cli.callbacks import end_failed_job
    from rotlearn.cli.training import report, train

    try:
        metrics = train(cfg)
    except (OSError, ValueError, ArithmeticError) as exc:  # the input's or the machine's fault
        end_failed_job(cfg.paths.output_dir, exc, "rotlearn-train")  # a bug keeps its traceback
        raise
    report(cfg, metrics)
    # what sweepers (Optuna) minimise: the validation median error, never a test number
    return metrics.get("val/err_median", metrics.get("val/loss", math.nan))


def _requeued() -> bool:
    """`rotlearn.cli.resume.requeued_on_slurm`, imported (with Lightning) only when asked."""
    from rotlearn.cli.resume import requeued_on_slurm

    return requeued_on_slurm()


def _refuse_an_invalid_new_run(argv: list[str]) -> list[str]:
    """Before Hydra creates anything for a new run (or sweep): check the command line
    (`rotlearn.config.command_line`: a bad option, key or value exits naming it; a sweep's
    other values too), refusing between its checks from files alone and its values' a folder
    Hydra would not use or a run or sweep directory that already exists and is not empty, then
    build a single run's datamodule and (on the meta device: nothing allocated) its model, so
    that a bad value leaves nothing behind (SystemExit naming the key).
    Returns the arguments for Hydra, with `+` before each component argument that its YAML does
    not list. A config that does not compose is left for Hydra to report (before it writes
    anything); flags such as --cfg or --info are Hydra's."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from rotlearn.cli.rundir import (
        refuse_an_absent_accelerator,
        refuse_an_existing_output_dir,
        runs_a_sweep,
    )
    from rotlearn.config import ConfigError, command_line

    def refuse_existing(cfg: DictConfig, args: list[str]) -> None:
        refuse_an_existing_output_dir(cfg, args, "train", "rotlearn-train", _requeued)

    def refuse_absent_devices(jobs: list[dict[str, Any]]) -> None:
        for values in jobs:  # every job of a sweep that is checked
            refuse_an_absent_accelerator(values)

    if any(a.startswith("-") and a not in ("-m", "--multirun") for a in argv):
        return argv
    try:
        cfg, argv = command_line(
            argv, "new-run", before_values=refuse_existing, after_values=refuse_absent_devices
        )
    except (HydraException, OmegaConfBaseException):
        return argv
    except ConfigError as exc:
        raise SystemExit(f"rotlearn-train: {exc} (nothing was written)") from None
    if runs_a_sweep(argv, cfg):
        return argv
    from rotlearn.cli.training import check_buildable

    try:
        check_buildable(cfg)
    except ConfigError as exc:
        raise SystemExit(f"rotlearn-train: {exc} (nothing was written)") from None
    return argv


def main() -> float | None:
    """Entry point of `rotlearn-train`; returns the validation median error (for sweepers), or
    None after `--help`."""
    argv = sys.argv[1:]
    if any(a in HELP_FLAGS for a in argv):
        print(usage(), end="")
        return None
    from rotlearn.cli import refusals_exit_at_once
    from rotlearn.cli.rundir import is_child_rank

    if not is_child_rank():  # another rank repeats rank 0's command line, already checked
        with refusals_exit_at_once():
            _refuse_two_modes(argv)
            _refuse_a_run_in_use(argv)
            sys.argv[1:] = _checked_command_line(argv)
    return _hydra_main()


def _refuse_two_modes(argv: list[str]) -> None:
    """SystemExit, in one line, where the command line gives two of Hydra's modes (`-m` and
    `--cfg job`, to see a sweep's config), or `--resolve` without `--cfg`, as Hydra reads its
    flags (`rundir.hydra_flags`: `-mc job` too): Hydra raised a ValueError with a traceback."""
    from rotlearn.cli.rundir import hydra_flags

    flags = hydra_flags(argv)
    if flags is None or flags.help or flags.hydra_help:  # help wins, as in Hydra
        return
    modes = [name for name, given in (("--run", flags.run), ("-m", flags.multirun),
             ("--cfg", flags.cfg is not None), ("--info", flags.info is not None),
             ("--shell-completion", flags.shell_completion)) if given]  # fmt: skip
    if len(modes) > 1:
        raise SystemExit(
            f"rotlearn-train: {' and '.join(modes)} do not go together (Hydra takes one of "
            "--run, -m, --cfg, --info, --shell-completion); to see one sweep job's config, give "
            "its values without -m: rotlearn-train <its values> --cfg job"
        )
    if flags.resolve and flags.cfg is None:
        raise SystemExit("rotlearn-train: --resolve goes with --cfg (it resolves the config "
                         "shown): rotlearn-train <values> --cfg job --resolve")  # fmt: skip


def _refuse_a_run_in_use(argv: list[str]) -> None:
    """A resume of a run that another process trains is refused at once, before the slow
    imports and checks (`rotlearn.locks`; the full check follows in `plan_resume`)."""
    from rotlearn.locks import RunLockedError, check_free

    values = [a.split("=", 1)[1] for a in argv if a.startswith("ckpt_path=")]
    if not values or values[-1] in ("", "null", "None", "last"):
        return
    run = Path(values[-1])
    if not run.is_dir():  # a checkpoint file: <run>/checkpoints/<name>.ckpt, or beside it
        run = run.parent.parent if run.parent.name == "checkpoints" else run.parent
    try:
        check_free(run)
    except RunLockedError as exc:
        raise SystemExit(f"rotlearn-train: refusing to resume: {exc}") from None


def _checked_command_line(argv: list[str]) -> list[str]:
    """The command line Hydra runs, after every check that must come before Hydra writes
    anything: a resume's (`rotlearn.cli.resume.plan_resume`), then its lock on the run and its
    earlier records moved to history/<n>/; a new run's (`_refuse_an_invalid_new_run`)."""
    if not any(a.startswith("ckpt_path=") for a in argv):  # before the resume's slow imports
        return _refuse_an_invalid_new_run(argv)
    from rotlearn.cli.resume import keep_earlier_records, plan_resume
    from rotlearn.locks import RunLockedError, hold_run

    plan = plan_resume(argv)
    if plan is None:
        return _refuse_an_invalid_new_run(argv)
    if any(a.startswith("-") for a in argv):  # --cfg, --info: Hydra shows, nothing trains
        return plan.args
    try:
        hold_run(plan.run_dir)  # until this process ends
    except RunLockedError as exc:
        raise SystemExit(f"rotlearn-train: refusing to resume: {exc}") from None
    except ValueError as exc:  # the lock file is a symlink or not a regular file
        raise SystemExit(f"rotlearn-train: refusing to resume {plan.run_dir}: {exc}") from None
    try:
        kept = keep_earlier_records(plan.run_dir)
    except (OSError, ValueError) as exc:  # a received run's history or config it cannot keep
        raise SystemExit(f"rotlearn-train: refusing to resume {plan.run_dir}: {exc}") from None
    if kept is not None:
        print(f"rotlearn-train: the run's earlier records are kept in {kept}", file=sys.stderr)
    return plan.args


if __name__ == "__main__":
    main()
