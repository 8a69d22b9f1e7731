"""Config checks derived from the constructors' signatures of the library classes a config builds.

The allowed keys of a node and, where the annotations say, their types come from
`inspect.signature` of its `_target_` (torch optimizers and schedulers, the Lightning Trainer,
loggers and callbacks, rotlearn's nets), so they follow the installed versions. rotlearn adds only
the value ranges it needs (`OPTIM_RANGES`, `TRAINER_RANGES`, ...). Only the targets listed in
`targets()` are checked: a config read from a run directory is not trusted, so nothing named in
it is imported here.
"""

from __future__ import annotations

import collections.abc
import difflib
import inspect
import os
import pathlib
import types
import typing
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from functools import cache
from typing import Any, Literal, Union

from rotlearn.cli.ranges import (
    CHECKPOINT_RANGES,
    NET_RANGES,
    OPTIM_RANGES,
    SCHEDULER_RANGES,
    TRAINER_RANGES,
)
from rotlearn.errors import ConfigError

__all__ = [
    "ConfigError",
    "Spec",
    "accepts",
    "check_keys",
    "check_values",
    "constructor_parameters",
    "describe",
    "targets",
]

HYDRA_KEYS = ("_target_", "_partial_", "_recursive_", "_convert_", "_args_")
MISSING = "???"  # OmegaConf's mark of a value the config must still set


def check_keys(key: str, names: Iterable[str], allowed: list[str]) -> None:
    """Refuse the first name not in `allowed`, suggesting the closest allowed one."""
    for name in names:
        if name not in allowed:
            close = difflib.get_close_matches(str(name), allowed, n=1)
            hint = f" (did you mean {key + '.' if key else ''}{close[0]}?)" if close else ""
            full = f"{key}.{name}" if key else name
            raise ConfigError(full, f"unknown{hint}; allowed: {', '.join(allowed)}")


# --- annotations -------------------------------------------------------------------------------

_LISTS = (
    list,
    tuple,
    collections.abc.Sequence,
    collections.abc.Iterable,
    collections.abc.Collection,
)
_PATHS = (pathlib.Path, pathlib.PurePath, os.PathLike)


def _is_union(ann: Any) -> bool:
    return typing.get_origin(ann) in (Union, types.UnionType)


def accepts(value: Any, ann: Any) -> bool:
    """Whether a plain config value (None, bool, int, float, str, list, dict) fits annotation
    `ann`. A mapping with a `_target_` fits any class (Hydra builds it); unknown forms fit."""
    if ann in (Any, inspect.Parameter.empty) or isinstance(ann, (str, typing.TypeVar)):
        return True
    if isinstance(value, dict) and "_target_" in value:
        return True
    origin, args = typing.get_origin(ann), typing.get_args(ann)
    if _is_union(ann):
        return any(accepts(value, a) for a in args)
    if origin is Literal:
        return any(value == a and type(value) is type(a) for a in args)
    if ann is type(None) or ann is None:
        return value is None
    if ann is bool:
        return isinstance(value, bool)
    if ann is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if ann is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if ann is str:
        return isinstance(value, str)
    if ann in _PATHS:
        return isinstance(value, str)
    if origin in _LISTS or ann in _LISTS:
        if not isinstance(value, (list, tuple)):
            return False
        if origin is tuple and args and args[-1] is not Ellipsis:
            return len(value) == len(args) and all(map(accepts, value, args))
        return not args or all(accepts(v, args[0]) for v in value)
    if origin in (dict, collections.abc.Mapping) or ann in (dict, collections.abc.Mapping):
        return isinstance(value, dict) and (
            len(args) != 2 or all(accepts(v, args[1]) for v in value.values())
        )
    # a library class (Accelerator, Tensor, timedelta) is no plain value; other forms fit
    return not isinstance(ann, type)


def describe(ann: Any) -> str:
    """A short reading of an annotation for a message: `int or None`, `one of 'a', 'b'`."""
    if _is_union(ann) or typing.get_origin(ann) is Literal:
        parts = typing.get_args(ann) if _is_union(ann) else (ann,)
        literals = [v for a in parts if typing.get_origin(a) is Literal for v in typing.get_args(a)]
        others = [describe(a) for a in parts if typing.get_origin(a) is not Literal]
        if literals:
            others.insert(0, "one of " + ", ".join(map(repr, literals)))
        return " or ".join(dict.fromkeys(others))
    if ann is type(None) or ann is None:
        return "None"
    origin, args = typing.get_origin(ann), typing.get_args(ann)
    if origin in _LISTS:
        return f"a list of {describe(args[0])}" if args else "a list"
    if origin in (dict, collections.abc.Mapping):
        return "a mapping"
    if ann in _PATHS:
        return "str"
    return getattr(ann, "__name__", str(ann).replace("typing.", ""))


# --- signatures --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Spec:
    """What a `_target_` accepts: `params` name -> (annotation, default); `supplied` are passed
    by rotlearn's code (not config keys); `ranges` name -> check(value) -> message or None."""

    target: Callable[..., Any]
    params: dict[str, tuple[Any, Any]]
    supplied: frozenset[str] = frozenset()
    ranges: Mapping[str, Callable[[Any], str | None]] = field(default_factory=dict)
    open: bool = False  # **kwargs going where we cannot see: other keys are left to the target

    @property
    def allowed(self) -> list[str]:
        return [n for n in self.params if n not in self.supplied]


def _hints(function: Callable[..., Any]) -> dict[str, Any]:
    try:
        return typing.get_type_hints(function)
    except Exception:  # a forward reference that cannot be resolved: read the raw annotations
        return {}


def parameters(target: Callable[..., Any]) -> dict[str, tuple[Any, Any]]:
    """Named arguments of `target` (a class: of its `__init__`): name -> (annotation, default or
    `inspect.Parameter.empty`)."""
    function = target.__init__ if inspect.isclass(target) else target
    hints = _hints(function)
    return {
        name: (hints.get(name, _from_default(p)), p.default)
        for name, p in inspect.signature(function).parameters.items()
        if name != "self" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
    }


def constructor_parameters(target: Callable[..., Any]) -> dict[str, tuple[Any, Any]]:
    """`parameters(target)`, following `**kwargs` to the base classes: a class whose `__init__`
    passes `**kwargs` on (`super().__init__(**kwargs)`) also takes its bases' arguments (the
    first definition of a name wins). Stops at the first `__init__` without `**kwargs`."""
    if not inspect.isclass(target):
        return parameters(target)
    found: dict[str, tuple[Any, Any]] = {}
    for cls in target.__mro__:
        if "__init__" not in vars(cls):
            continue
        for name, value in parameters(cls).items():
            found.setdefault(name, value)
        if not takes_kwargs(cls):
            break
    return found


def _from_default(p: inspect.Parameter) -> Any:
    """An unannotated argument's type, read from its default (bool, a number or str)."""
    if p.annotation is not p.empty:
        return p.annotation
    if isinstance(p.default, bool):
        return bool
    return {int: float, float: float, str: str}.get(type(p.default), Any)


def takes_kwargs(target: Callable[..., Any]) -> bool:
    function = target.__init__ if inspect.isclass(target) else target
    return any(p.kind is p.VAR_KEYWORD for p in inspect.signature(function).parameters.values())


def check_values(key: str, values: dict[str, Any], spec: Spec) -> None:
    """Check a resolved node (`values`, without Hydra's `_target_`-style keys) against `spec`:
    unknown keys, missing required arguments, rotlearn's ranges, then the annotations."""
    if not spec.open:
        check_keys(key, values, spec.allowed)
    for name in spec.allowed:
        required = spec.params[name][1] is inspect.Parameter.empty
        if required and (name not in values or values[name] == MISSING):
            raise ConfigError(f"{key}.{name}", "missing (the constructor needs it)")
    for name, value in values.items():
        if name in spec.ranges and (message := spec.ranges[name](value)):
            raise ConfigError(f"{key}.{name}", f"{message}, got {value!r}")
        annotation = spec.params.get(name, (Any,))[0]
        if not accepts(value, annotation):
            raise ConfigError(f"{key}.{name}", f"expected {describe(annotation)}, got {value!r}")


# --- rotlearn's ranges -------------------------------------------------------------------------


def _classes(module: Any, base: type, prefix: str) -> dict[str, type]:
    found = {}
    for name in getattr(module, "__all__", dir(module)):
        obj = getattr(module, name, None)
        if inspect.isclass(obj) and issubclass(obj, base) and obj is not base:
            found[f"{prefix}.{name}"] = obj
    return found


def _summary_writer() -> dict[str, tuple[Any, Any]]:
    try:  # TensorBoardLogger hands its **kwargs to the SummaryWriter
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return {}
    return {k: v for k, v in parameters(SummaryWriter).items() if k != "log_dir"}


@cache
def targets() -> dict[str, dict[str, Spec]]:
    """Node (`optim`, `scheduler`, `trainer`, `net`, `logger`, `callbacks`) -> `_target_` ->
    `Spec`. `logger` and `callbacks` apply to each entry of those nodes."""
    import lightning.pytorch as pl
    import torch
    from lightning.pytorch import callbacks, loggers

    from rotlearn import nets
    from rotlearn.lit import EpochTimer, TensorBoardRunLogger

    def specs(classes: dict[str, type], supplied=(), ranges=None, extra=None) -> dict[str, Spec]:
        extra = extra or {}  # where a class's **kwargs go, when we know
        return {
            name: Spec(
                cls,
                {**parameters(cls), **extra.get(cls, {})},
                frozenset(supplied),
                ranges or {},
                open=takes_kwargs(cls) and cls not in extra,
            )
            for name, cls in classes.items()
        }

    scheduler_base = torch.optim.lr_scheduler.LRScheduler
    callback_classes = _classes(callbacks, pl.Callback, "lightning.pytorch.callbacks")
    callback_classes["rotlearn.lit.EpochTimer"] = EpochTimer
    return {
        "optim": specs(
            _classes(torch.optim, torch.optim.Optimizer, "torch.optim"), ["params"], OPTIM_RANGES
        ),
        "scheduler": specs(
            _classes(torch.optim.lr_scheduler, scheduler_base, "torch.optim.lr_scheduler"),
            ["optimizer"],
            SCHEDULER_RANGES,
        ),
        "trainer": specs(
            {"lightning.pytorch.Trainer": pl.Trainer, "lightning.Trainer": pl.Trainer},
            ["callbacks", "logger"],
            TRAINER_RANGES,
        ),
        "net": specs(_classes(nets, torch.nn.Module, "rotlearn.nets"), ranges=NET_RANGES),
        "logger": specs(
            {
                **_classes(loggers, pl.loggers.Logger, "lightning.pytorch.loggers"),
                "rotlearn.lit.TensorBoardRunLogger": TensorBoardRunLogger,
            },
            extra={
                loggers.TensorBoardLogger: _summary_writer(),
                TensorBoardRunLogger: {
                    **parameters(loggers.TensorBoardLogger),
                    **_summary_writer(),
                },
            },
        ),
        "callbacks": specs(callback_classes)
        | specs(
            {"lightning.pytorch.callbacks.ModelCheckpoint": callbacks.ModelCheckpoint},
            ranges=CHECKPOINT_RANGES,
        ),
    }
