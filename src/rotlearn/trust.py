"""Files are data, never code: the allowlist of what a config read from a file may build.

A Hydra config names the class or function that builds each component in its `_target_` key, and
`hydra.utils.instantiate` imports and calls whatever is named there: `torch.load` with
`weights_only: false`, `builtins.open` with `mode: w`, `numpy.load` with `allow_pickle: true`.
Checkpoints, run directories and datasets can come from anyone, so every config rotlearn rebuilds
from a file goes through `trusted_config` first. It walks every node, nested dicts and lists
included, BEFORE anything is instantiated, and refuses the whole config, naming the key path and
the target, when a `_target_` is not on the allowlist, a node passes arguments by position
(`_args_`: what a component may write is checked by argument name), or a string could still be
resolved into something else (an OmegaConf interpolation `${...}`). The user's own command line
is trusted and is never checked.

The allowlist:

- rotlearn's own components: the classes and functions marked with `@config_target` where they are
  defined (a new dataset or net marks itself; no list to edit elsewhere). A target
  `rotlearn.<module>.<Name>` is looked up by importing that rotlearn module (rotlearn's own code)
  and is trusted only if the object itself carries the mark (not inherited).
- the few library classes rotlearn's configs use: `LIBRARY_TARGETS`.
"""

from __future__ import annotations

import importlib
import os
import re
from collections.abc import Callable
from typing import Any, TypeVar

__all__ = [
    "LIBRARY_TARGETS",
    "UntrustedConfigError",
    "check_config",
    "config_target",
    "is_trusted_target",
    "trusted_config",
]

_MARK = "__rotlearn_config_target__"
_DOTTED = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)+")

# Library classes that rotlearn's configs (conf/) build, and their usual alternatives.
LIBRARY_TARGETS = frozenset(
    {
        *(
            f"torch.optim.{name}"
            for name in ("Adam", "AdamW", "SGD", "RMSprop", "Adagrad", "NAdam", "RAdam")
        ),
        *(
            f"torch.optim.lr_scheduler.{name}"
            for name in (
                "CosineAnnealingLR",
                "CosineAnnealingWarmRestarts",
                "StepLR",
                "MultiStepLR",
                "ExponentialLR",
                "LinearLR",
                "OneCycleLR",
                "ReduceLROnPlateau",
            )
        ),
        "lightning.pytorch.Trainer",
        "lightning.pytorch.loggers.TensorBoardLogger",
        "lightning.pytorch.loggers.CSVLogger",
        *(
            f"lightning.pytorch.callbacks.{name}"
            for name in (
                "ModelCheckpoint",
                "LearningRateMonitor",
                "EarlyStopping",
                "TQDMProgressBar",
                "RichProgressBar",
                "ModelSummary",
                "Timer",
                "StochasticWeightAveraging",
            )
        ),
    }
)

T = TypeVar("T", bound=Callable[..., Any])


class UntrustedConfigError(ValueError):
    """A config read from a file names something that rotlearn does not build from files."""


def config_target(obj: T) -> T:
    """Mark a rotlearn class or function as one that a config read from a file may name as its
    `_target_`. Use it only on components whose construction does nothing but build the
    component (no file writes, no imports chosen by arguments)."""
    setattr(obj, _MARK, True)
    return obj


def is_trusted_target(target: object) -> bool:
    """Whether `target` (a `_target_` value) is on the allowlist (module docstring)."""
    if not isinstance(target, str) or not _DOTTED.fullmatch(target):
        return False
    if target in LIBRARY_TARGETS:
        return True
    module_name, _, name = target.rpartition(".")
    if module_name != "rotlearn" and not module_name.startswith("rotlearn."):
        return False
    try:
        module = importlib.import_module(module_name)  # rotlearn's own modules only
    except ImportError:
        return False
    obj = getattr(module, name, None)
    return bool(getattr(obj, "__dict__", {}).get(_MARK, False))


def _path(parent: str, key: object) -> str:
    return f"{parent}.{key}" if parent else str(key)


def check_config(tree: Any, source: str | os.PathLike) -> None:
    """Refuse a config (plain dicts, lists and scalars) that could run code when instantiated.

    Args:
        tree: the config as plain data (e.g. `OmegaConf.to_container(cfg, resolve=True)` or
            what a checkpoint holds).
        source: the file it came from, for messages.

    Raises:
        UntrustedConfigError: naming the file, the key path and the offending target or string:
            a `_target_` that is not on the allowlist (or not a string), positional arguments
            (`_args_`: the run-directory checks see arguments by name, such as a checkpoint
            callback's `dirpath`), a string holding an OmegaConf interpolation `${`, a key that
            is not a string, or nesting deeper than 64.
    """
    stack: list[tuple[str, Any, int]] = [("", tree, 0)]
    positional = None
    while stack:
        path, node, depth = stack.pop()
        if depth > 64:
            raise UntrustedConfigError(f"{source}: config key {path}: nested too deeply")
        if isinstance(node, dict):
            target = node.get("_target_")
            if "_target_" in node and not is_trusted_target(target):
                raise UntrustedConfigError(
                    f"{source}: config key {_path(path, '_target_')}: {target!r} is not on "
                    "rotlearn's allowlist of components a file may build; nothing was built "
                    "(see README, Security)"
                )
            if "_args_" in node:  # a path passed by position: no check by name could see it
                positional = positional or _path(path, "_args_")  # named after any target in it
            for key, value in node.items():
                if not isinstance(key, str):
                    raise UntrustedConfigError(
                        f"{source}: config key {_path(path, key)}: keys must be strings"
                    )
                stack.append((_path(path, key), value, depth + 1))
        elif isinstance(node, (list, tuple)):
            stack.extend((_path(path, i), value, depth + 1) for i, value in enumerate(node))
        elif isinstance(node, str) and "${" in node:
            raise UntrustedConfigError(
                f"{source}: config key {path}: {node!r} is an interpolation; a config read from "
                "a file must hold resolved values only"
            )
    if positional is not None:
        raise UntrustedConfigError(
            f"{source}: config key {positional}: positional arguments are not taken from a file "
            "(each argument is checked by its name: a run to be resumed or loaded gives its "
            "arguments by name, never in _args_); nothing was built"
        )


def trusted_config(tree: Any, source: str | os.PathLike):
    """A config read from a file, as a `DictConfig` that is safe to instantiate.

    Args:
        tree: a dict of plain data, or a `DictConfig` (resolved first: its interpolations are
            evaluated, then the result is checked).
        source: the file it came from, for messages.

    Returns:
        A `DictConfig` with no interpolations whose every `_target_` is on the allowlist.

    Raises:
        UntrustedConfigError: see `check_config`; also when `tree` is not a mapping or a
            `DictConfig` cannot be resolved.
    """
    from omegaconf import DictConfig, OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    if isinstance(tree, DictConfig):
        try:
            tree = OmegaConf.to_container(tree, resolve=True)
        except OmegaConfBaseException as exc:
            raise UntrustedConfigError(f"{source}: the config cannot be resolved: {exc}") from None
    if not isinstance(tree, dict):
        raise UntrustedConfigError(
            f"{source}: expected a config mapping, got {type(tree).__name__}"
        )
    check_config(tree, source)
    return OmegaConf.create(tree)
