"""Every key and value of a composed train config, checked before anything is built or written.

`validate(cfg)` makes two passes over the resolved config, each node checked against the
constructor its `_target_` names (rotlearn's components marked `@config_target`, torch's
optimizers and schedulers, Lightning's trainer, loggers and callbacks; a user's own class is left
to its constructor):

1. `check_keys`, from files alone (the config, the components' source read by
   `rotlearn.config.source`, the data folders): unknown keys (with the nearest known one and the
   allowed ones), required arguments, and the data root and the layout its datamodule declares
   (a `layout` class attribute: paths under `root`, `{key}` standing for each value of that key,
   `key=value:` first where only that value needs the path). No torch, no Lightning: these
   answers come within a second.
2. `check_values` imports the components and validates each value with pydantic against the
   annotation of its argument: `Literal`, unions, `Annotated[int, Gt(0)]` (annotated-types
   constraints, declared on the constructors' own signatures), plus `LIBRARY_CONSTRAINTS` for the
   library classes rotlearn narrows. Then the rules that span keys, each declared by the
   component that needs it: the head and the loss are built (the registry checks the name and
   size; a likelihood loss refuses a head without its belief), `calibrate` asks
   `TemperatureScaling.refusal`, and a component with a `check_config(config)` class method
   (`OODEvaluation`: an image-pair datamodule) judges the whole config.

Errors are `ConfigError`s naming the full key, in one line.
"""

from __future__ import annotations

import difflib
import inspect
import itertools
import re
import string
from functools import cache
from pathlib import Path
from typing import Annotated, Any, Literal

import annotated_types
from annotated_types import Ge, Gt, Le, Len, Lt, MinLen
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from rotlearn.config.source import MISSING, Parameter, class_attribute, is_marked, parameters
from rotlearn.errors import ConfigError

__all__ = ["PATHS", "TOP_LEVEL", "allowed_keys", "check_keys", "data_paths", "check_values", "library_constraints"]

HYDRA_KEYS = ("_target_", "_partial_", "_recursive_", "_convert_", "_args_")
NODES = ("model", "rep", "net", "data", "loss", "optim", "scheduler", "trainer")
COLLECTIONS = ("logger", "callbacks")  # name -> node
OPTIONAL = ("scheduler",)
LIBRARIES = ("torch.optim.", "lightning.")  # library classes checked by their signatures
SUPPLIED = {"optim": {"params"}, "scheduler": {"optimizer"}, "trainer": {"callbacks", "logger"}}
KWARGS_TO = {"lightning.pytorch.loggers.TensorBoardLogger": "torch.utils.tensorboard.SummaryWriter"}

# conf/train.yaml's own keys (and sweep=lr's trial, trials, sweep_seed, lr_range)
TOP_LEVEL: dict[str, Any] = {
    "seed": Annotated[int, Ge(0), Le(2**32 - 1)],  # numpy's seed range
    "ckpt_path": str | None,
    "test_ckpt": Literal["last", "best"],
    "calibrate": bool,
    "float32_matmul_precision": Literal["highest", "high", "medium"],
    "trial": Annotated[int, Ge(0), Le(2**31)],
    "trials": Annotated[int, Ge(1), Le(2**31)],
    "sweep_seed": int,
    "lr_range": Annotated[list[Annotated[float, Gt(0)]], Len(2, 2)],
    "report": dict | None,  # rotlearn-report's layout (an experiment's report node)
}
PATHS = {"output_dir": Annotated[str, MinLen(1)]}  # where a run writes (Hydra's run directory)
REQUIRED = ("seed", "paths")


def plain(cfg: DictConfig) -> dict[str, Any]:
    """The config resolved to plain data (without `hydra`); `ConfigError` names a key whose
    interpolation cannot be resolved."""
    cfg = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    try:
        return OmegaConf.to_container(cfg, resolve=True)
    except OmegaConfBaseException:
        for name in TOP_LEVEL:  # a value that interpolations read (sweep=lr's trial, trials)
            node = cfg._get_node(name)
            if node is not None and not OmegaConf.is_interpolation(cfg, name):
                _check(name, OmegaConf.to_object(node) if OmegaConf.is_config(node) else node._value(), TOP_LEVEL[name])
        raw = OmegaConf.to_container(cfg, resolve=False)
        for key in _leaves(raw):
            try:
                OmegaConf.select(cfg, key, throw_on_resolution_failure=True)
            except OmegaConfBaseException as exc:
                raise ConfigError(key, f"cannot be resolved: {str(exc).splitlines()[0]}") from None
        raise


def _leaves(node: Any, prefix: str = ""):
    items = node.items() if isinstance(node, dict) else enumerate(node)
    for key, value in items:
        path = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, dict | list):
            yield from _leaves(value, path)
        else:
            yield path


def refuse_unknown(key: str, names: list[str], allowed: list[str]) -> None:
    """Refuse the first of `names` (keys of the node `key`) not in `allowed`, with the nearest."""
    for name in names:
        if name not in allowed:
            close = difflib.get_close_matches(str(name), allowed, n=1)
            near = f"; did you mean {key + '.' if key else ''}{close[0]}?" if close else ""
            full = f"{key}.{name}" if key else str(name)
            raise ConfigError(full, f"unknown key{near}; allowed: {', '.join(allowed) or 'none'}")


def _nodes(values: dict[str, Any]) -> list[tuple[str, str, dict[str, Any]]]:
    """(key, group, node) of every component node; refuses a node that is not a mapping with a
    `_target_` (None where optional)."""
    found = []
    for key in NODES:
        node = values.get(key)
        if node is None and key in OPTIONAL:
            continue
        if not isinstance(node, dict) or "_target_" not in node:
            raise ConfigError(key, f"must be a mapping with a _target_, got {node!r}")
        found.append((key, key, node))
    for group in COLLECTIONS:
        entries = values.get(group) or {}
        if not isinstance(entries, dict):
            raise ConfigError(group, f"must be a mapping of names to nodes, got {entries!r}")
        for name, node in entries.items():
            if not isinstance(node, dict) or "_target_" not in node:
                drop = f" (to drop it: ~{group}.{name})" if node is None else ""
                raise ConfigError(f"{group}.{name}", f"must be a mapping with a _target_{drop}")
            found.append((f"{group}.{name}", group, node))
    return found


@cache
def _parameters(target: str) -> tuple[Parameter, ...] | None:
    """The arguments of a node's `_target_` that a config may set (None: not checked here):
    a rotlearn component's, its `**kwargs` followed to its bases; a library class's own, and
    where its `**kwargs` go (`KWARGS_TO`)."""
    if is_marked(target):
        return parameters(target)[0]
    found = parameters(target, bases=False) if target.startswith(LIBRARIES) else None
    if found is None or found[1] and target not in KWARGS_TO:
        return None  # not ours, or **kwargs that go where we cannot see
    extra = parameters(KWARGS_TO[target])[0] if found[1] else ()
    names = {p.name for p in found[0]}
    return (*found[0], *(p for p in extra if p.name not in names))


def allowed_keys(target: str, group: str) -> list[str] | None:
    """The keys a node with this `_target_` takes in `group` (None: not checked here), less the
    arguments rotlearn passes itself (`SUPPLIED`)."""
    found = _parameters(target)
    if found is None:
        return None
    return [p.name for p in found if p.name not in SUPPLIED.get(group, ())]


_CONDITION = re.compile(r"(?:(\w+)=([^:/{}]+):\s*)?(.*)")  # [key=value: ]path


def data_paths(node: dict[str, Any]) -> list[tuple[str, Path]]:
    """(config key, path) of what a data node's root must hold: the root, then each path of its
    datamodule's `layout` (a `{key}` standing for each value of that key; `key=value: path`
    where only that value needs it). Empty for a datamodule without a `root`."""
    if "root" not in node:
        return []
    root = Path(str(node["root"]))
    found = [("data.root", root)]
    for template in class_attribute(node["_target_"], "layout") or []:
        key, value, path = _CONDITION.fullmatch(template).groups()
        if key and str(node.get(key)) != value:
            continue
        fields = [f for _, f, _, _ in string.Formatter().parse(path) if f]
        choices = [node[f] if isinstance(node[f], list) else [node[f]] for f in fields]
        for combination in itertools.product(*choices):
            where = f"data.{fields[0]}" if fields else "data.root"
            found.append((where, root / path.format(**dict(zip(fields, combination)))))
    return found


def _check_layout(node: dict[str, Any]) -> None:
    paths = data_paths(node)
    layout = class_attribute(node["_target_"], "layout") or []
    shown = [re.sub(r"\{(\w+)[^}]*\}", r"<\1>", _CONDITION.fullmatch(t)[3]) for t in layout]
    expected = f"; it must hold {', '.join(dict.fromkeys(shown))} (data/README.md)" if layout else ""
    if paths and not paths[0][1].is_dir():
        raise ConfigError("data.root", f"no directory {paths[0][1]}{expected}")
    for key, path in paths[1:]:
        if not path.exists():
            raise ConfigError(key, f"{path} does not exist{expected}")


def check_keys(values: dict[str, Any]) -> None:
    """Pass 1 (files only): the top-level keys, every node's keys and required arguments, and
    the data root and layout."""
    refuse_unknown("", list(values), sorted([*TOP_LEVEL, *NODES, *COLLECTIONS, "paths"]))
    for name in REQUIRED:
        if name not in values:
            raise ConfigError(name, "is missing")
    if not isinstance(values["paths"], dict):
        raise ConfigError("paths", f"must be a mapping with output_dir, got {values['paths']!r}")
    refuse_unknown("paths", list(values["paths"]), list(PATHS))
    for key, group, node in _nodes(values):
        allowed = allowed_keys(node["_target_"], group)
        if allowed is None:
            continue
        refuse_unknown(key, [k for k in node if k not in HYDRA_KEYS], allowed)
        for parameter in _parameters(node["_target_"]):
            value = node.get(parameter.name, parameter.default)
            if parameter.name in allowed and value == MISSING:
                raise ConfigError(f"{key}.{parameter.name}", "missing (the constructor needs it)")
        if key == "data":
            _check_layout(node)


# --- pass 2: values ------------------------------------------------------------------------


@cache
def library_constraints() -> dict[str, dict[str, Any]]:
    """What rotlearn requires of the library classes' arguments beyond their annotations, per
    group (or `_target_`). A `description` says what is expected where a union would not."""
    from pydantic import AfterValidator, Field

    positive, non_negative = Annotated[float, Gt(0)], Annotated[float, Ge(0)]
    count, index = Annotated[int, Gt(0)], Annotated[int, Ge(0)]

    def registered(kind: str) -> AfterValidator:
        def check(name: str) -> str:
            from lightning.pytorch.accelerators import AcceleratorRegistry
            from lightning.pytorch.strategies import StrategyRegistry

            registry = AcceleratorRegistry if kind == "an accelerator" else StrategyRegistry
            known = sorted({"auto", *registry.keys(), *(["gpu"] if registry is AcceleratorRegistry else [])})
            if name not in known:
                raise ValueError(f"should be the name of {kind} Lightning knows: {', '.join(known)}")
            return name

        return AfterValidator(check)

    batches = "an integer >= 0, a fraction in [0, 1], or null"
    limit = Annotated[index | Annotated[float, Ge(0), Le(1)] | None, Field(description=batches)]
    devices = (
        "a positive integer, -1 (every device), 'auto', a string of device indices, or a list of "
        "device indices"
    )
    return {
        "optim": {
            "lr": positive,
            "weight_decay": non_negative,
            "eps": non_negative,
            "momentum": non_negative,
            "betas": Annotated[list[Annotated[float, Ge(0), Lt(1)]], Len(2, 2)],
        },
        "scheduler": {"step_size": count, "T_max": count, "gamma": positive},
        "trainer": {
            "max_epochs": Annotated[
                count,
                Field(description="a positive integer (Lightning reads -1 as 'train forever', 0 "
                      "as no training)"),
            ],  # fmt: skip
            "min_epochs": index | None,
            "devices": Annotated[
                Literal[-1, "auto"]
                | count
                | Annotated[str, Field(pattern=r"^\s*\d+(\s*,\s*\d+)*\s*,?\s*$")]
                | Annotated[list[index], MinLen(1)],
                Field(description=devices),
            ],
            "accelerator": Annotated[str, registered("an accelerator")],
            "strategy": Annotated[str, registered("a strategy")],
            "num_nodes": count,
            "log_every_n_steps": count | None,
            "check_val_every_n_epoch": count | None,
            "accumulate_grad_batches": count,
            "reload_dataloaders_every_n_epochs": index,
            "gradient_clip_val": non_negative | None,
            "gradient_clip_algorithm": Literal["norm", "value"] | None,
            "limit_train_batches": limit,
            "limit_val_batches": limit,
            "limit_test_batches": limit,
            "limit_predict_batches": limit,
            "fast_dev_run": Annotated[
                bool | index, Field(description="true, false or a number of batches >= 0")
            ],
            "num_sanity_val_steps": Annotated[
                Annotated[int, Ge(-1)] | None,
                Field(description="an integer >= -1 (-1: every validation batch) or null"),
            ],
        },
        "lightning.pytorch.callbacks.ModelCheckpoint": {
            "mode": Literal["min", "max"],
            "save_top_k": Annotated[int, Ge(-1)],
            "every_n_epochs": index | None,
            "every_n_train_steps": index | None,
        },
    }


def _annotation(owner: str, name: str) -> Any:
    """The annotation of argument `name` of `owner` (a class: its `__init__`), constraints
    included; an unannotated argument's type is read from its default (bool, number, str)."""
    from hydra.utils import get_object

    function = get_object(owner)
    function = inspect.unwrap(function.__init__ if inspect.isclass(function) else function)
    parameter = inspect.signature(function).parameters[name]
    if parameter.annotation is parameter.empty:
        default = parameter.default
        return bool if isinstance(default, bool) else {int: float, float: float, str: str}.get(
            type(default), Any
        )
    if not isinstance(parameter.annotation, str):
        return parameter.annotation
    constraints = {n: getattr(annotated_types, n) for n in annotated_types.__all__}
    try:  # the constraints' names are imported for type checkers only: supplied here
        return eval(parameter.annotation, function.__globals__, constraints)  # noqa: S307
    except Exception:  # a name the module imports for type checking only: any value
        return Any


@cache
def _adapter(annotation: Any):
    """A strict pydantic validator of `annotation`; a mapping with a `_target_` passes (Hydra
    builds it into the object the annotation asks for)."""
    from pydantic import ConfigDict, TypeAdapter, WrapValidator

    def nested(value: Any, handler: Any) -> Any:
        if isinstance(value, dict) and "_target_" in value:
            return value
        result = handler(value)
        if isinstance(value, float) and type(result) is int:  # 32.0 for Literal[32]
            raise ValueError(f"should be an integer, not {value!r}")
        return result

    config = ConfigDict(strict=True, arbitrary_types_allowed=True)
    try:
        return TypeAdapter(Annotated[annotation, WrapValidator(nested)], config=config)
    except TypeError:  # a type pydantic cannot check (PydanticSchemaGenerationError): any value
        return TypeAdapter(Any)


def _check(key: str, value: Any, annotation: Any) -> None:
    from pydantic import ValidationError
    from pydantic.fields import FieldInfo

    try:
        _adapter(annotation).validate_python(value)
    except ValidationError as exc:
        notes = [m.description for m in getattr(annotation, "__metadata__", ()) if
                 isinstance(m, FieldInfo) and m.description]  # fmt: skip
        if notes:
            raise ConfigError(key, f"must be {notes[0]}, got {value!r}") from None
        said = []
        for error in exc.errors(include_url=False):
            at = "".join(f"[{i}]" for i in error["loc"] if isinstance(i, int))
            text = error["msg"].removeprefix("Value error, ").replace(" after validation", "")
            subject, should, rest = text.partition("should ")  # "Input should be ...", "List ..."
            text = rest if should and len(subject.split()) <= 1 else f"be {text}"
            said.append(f"{text} (at {at})" if at else text)
        said = list(dict.fromkeys(said))
        if all(t.startswith("be ") for t in said):
            said = ["be " + " or ".join(t[3:] for t in said)]
        raise ConfigError(key, f"should {' or '.join(said)}, got {value!r}") from None


def _build(values: dict[str, Any], key: str) -> Any:
    from hydra.utils import instantiate

    try:
        return instantiate(values[key])
    except ConfigError as exc:
        raise exc.within(key) from None
    except Exception as exc:
        cause = exc.__cause__
        if isinstance(cause, ConfigError):
            raise cause.within(key) from None
        raise


def check_values(values: dict[str, Any]) -> None:
    """Pass 2 (imports the components): every value against its annotation, then the rules that
    span keys."""
    from hydra.utils import get_object

    from rotlearn.lit.calibration import TemperatureScaling

    for name, annotation in TOP_LEVEL.items():
        if name in values:
            _check(name, values[name], annotation)
    for name, annotation in PATHS.items():
        _check(f"paths.{name}", values["paths"].get(name), annotation)
    nodes = _nodes(values)
    library = library_constraints()
    for key, group, node in nodes:
        target = node["_target_"]
        if allowed_keys(target, group) is None:
            continue
        owners = {p.name: p.owner for p in _parameters(target)}
        narrowed = library.get(group, {}) | library.get(target, {})
        for name, value in node.items():
            if name not in HYDRA_KEYS:
                annotation = narrowed.get(name) or _annotation(owners[name], name)
                _check(f"{key}.{name}", value, annotation)
    head = _build(values, "rep")
    _build(values, "loss")
    model_head = head if "head" in values["model"] else None
    if values.get("calibrate") and (why := TemperatureScaling.refusal(model_head, values["model"])):
        raise ConfigError("calibrate", why)
    for key, _, node in nodes:
        component = get_object(node["_target_"]) if is_marked(node["_target_"]) else None
        hook = getattr(component, "check_config", None)
        if hook is not None and (why := hook(values)):
            raise ConfigError(key, why)
