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
    for line in text.splitlines():
        match = re.match(r"^(\w+):\s*(\S.*)$", line)
        if match and match.group(1) not in ("defaults", "hydra", "paths"):
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
    from rotlearn.cli.training import report, train

    metrics = train(cfg)
    report(cfg, metrics)
    # what sweepers (Optuna) minimise: the validation median error, never a test number
    return metrics.get("val/err_median", metrics.get("val/loss", math.nan))


def _checked(argv: list[str]) -> list[str]:
    """The command line of a new run (or sweep), validated before Hydra creates its directory
    (`rotlearn.config.command_line`): a bad option, key or value exits naming it, having written
    nothing. Returns the arguments for Hydra, with `+` before each component argument that its
    YAML does not list. Flags such as --cfg and resumes (`rotlearn.cli.resume` validates those)
    pass unchecked; a command line that does not compose is left for Hydra to report."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from rotlearn.config import ConfigError, command_line

    flags = [a for a in argv if a.startswith("-") and a not in ("-m", "--multirun")]
    if flags or any(a.startswith("ckpt_path=") for a in argv):
        return argv
    try:
        return command_line(argv, "new-run")
    except (HydraException, OmegaConfBaseException):
        return argv
    except ConfigError as exc:
        raise SystemExit(f"rotlearn-train: {exc} (nothing was written)") from None


def main() -> float | None:
    """Entry point of `rotlearn-train`; returns the validation median error (for sweepers), or
    None after `--help`."""
    argv = sys.argv[1:]
    if any(a in HELP_FLAGS for a in argv):
        print(usage(), end="")
        return None
    argv = _checked(argv)
    from rotlearn.cli.resume import keep_earlier_records, resume_arguments

    args = resume_arguments(argv)
    if args != argv:  # a resume that will train: its last argument is hydra.run.dir=<run dir>
        kept = keep_earlier_records(Path(args[-1].split("=", 1)[1]))
        if kept is not None:
            print(f"rotlearn-train: the run's earlier records are kept in {kept}", file=sys.stderr)
    sys.argv[1:] = args
    return _hydra_main()


if __name__ == "__main__":
    main()
