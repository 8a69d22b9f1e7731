"""Every key and value of a composed train config, checked before anything is built or written.

A node is checked against the constructor its `_target_` names (rotlearn's components, marked
`@config_target`; torch's optimizers and schedulers; Lightning's trainer, loggers and callbacks;
a user's own class is left to its constructor). `check_keys` decides from files alone: keys and
required arguments from the source (`rotlearn.config.source`), the data root and what its
datamodule's `layout` says it holds (`{key}`: each value of that key; `key=value:` first, a path
only that value needs). `check_values` validates each value with pydantic against its argument's
annotation, constraints included (`Annotated[int, Gt(0)]`; library classes: `library_constraints`),
read from the source where it names only typing constructs (a refusal before torch loads), else
imported; then the rules that span keys, each declared by the component that needs it: a component's
`config_needs` ((key, class, what), ...: the node at `key` defines that class's methods; read
from the source by `check_keys`), the head and the loss are built (the head registry checks name
and size, a likelihood loss its head), and `calibrate: true` asks the temperature fit's
`rotlearn.bingham.temperature.temperature_refusal` (before Lightning is imported).
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

from annotated_types import Ge, Gt, Le, Len, Lt, MinLen
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from rotlearn.config.source import (
    MISSING,
    Parameter,
    class_attribute,
    is_marked,
    parameters,
    provides,
    typing_names,
)
from rotlearn.errors import ConfigError, validation_words
from rotlearn.paths import TESTED_WEIGHTS

__all__ = [
    "TOP_LEVEL",
    "arguments",
    "check_keys",
    "check_values",
    "data_paths",
    "library_constraints",
    "plain",
]

HYDRA_KEYS = ("_target_", "_partial_", "_recursive_", "_convert_", "_args_")
NODES = (
    "model",
    "rep",
    "net",
    "data",
    "loss",
    "optim",
    "scheduler",
    "trainer",
)  # scheduler: or null
COLLECTIONS = ("logger", "callbacks")  # name -> node
LIBRARIES = ("torch.optim.", "torch.utils.tensorboard.", "lightning.")  # by own signatures
SUPPLIED = {"optim": {"params"}, "scheduler": {"optimizer"}, "trainer": {"callbacks", "logger"},
            "logger": {"log_dir"}}  # rotlearn passes these  # fmt: skip
KWARGS_TO = {  # where a class's **kwargs go
    "rotlearn.lit.TensorBoardRunLogger": "lightning.pytorch.loggers.TensorBoardLogger",
    "lightning.pytorch.loggers.TensorBoardLogger": "torch.utils.tensorboard.SummaryWriter",
}
TOP_LEVEL: dict[str, Any] = {  # conf/train.yaml's keys (and sweep=lr's); seed and paths required
    "seed": Annotated[int, Ge(0), Le(2**32 - 1)],  # numpy's seed range
    "paths": dict[Literal["output_dir"], Annotated[str, MinLen(1)]],
    "ckpt_path": str | None,
    "test_ckpt": Literal[tuple(TESTED_WEIGHTS)],
    "calibrate": bool | Literal["auto"],  # auto: for every head with a belief
    "float32_matmul_precision": Literal["highest", "high", "medium"],
    "trial": Annotated[int, Ge(0), Le(2**31)],
    "trials": Annotated[int, Ge(1), Le(2**31)],
    "sweep_seed": int,
    "lr_range": Annotated[list[Annotated[float, Gt(0)]], Len(2, 2)],
    "report": dict | None,  # rotlearn-report's layout (`rotlearn.report.layout`)
}
_CONDITION = re.compile(r"(?:(\w+)=([^:/{}]+):\s*)?(.*)")  # a layout path: [key=value: ]path
_PLAIN = re.compile(r"(?!\.\.?$)[^/\\\0]+")  # a file name: no separator, not . or ..


def plain(cfg: DictConfig) -> dict[str, Any]:
    """The config as resolved plain data, without `hydra`; `ConfigError` names a top-level value
    that an interpolation cannot use (sweep=lr's trials), else the key that does not resolve."""
    cfg = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    try:
        return OmegaConf.to_container(cfg, resolve=True)
    except OmegaConfBaseException as exc:
        raw = OmegaConf.to_container(cfg)
        for name in (n for n in TOP_LEVEL if n in raw and "${" not in str(raw[n])):
            _check(name, raw[name], TOP_LEVEL[name])
        raise ConfigError(exc.full_key, f"cannot be resolved: {exc.msg.splitlines()[0]}") from None


def refuse_unknown(
    key: str, names: list[str], allowed: list[str], note: str = "", elsewhere: str = ""
) -> None:
    """Refuse the first of `names` (keys of node `key`) not in `allowed`, naming the nearest,
    else `elsewhere` (a full key the name may have meant), then `note`."""
    for name in (n for n in names if n not in allowed):
        close = difflib.get_close_matches(str(name), allowed, n=1)
        near = (f"{key}." if key else "") + close[0] if close else elsewhere
        hint = f"; did you mean {near}?" if near else ""
        full = f"{key}.{name}" if key else str(name)
        raise ConfigError(full, f"unknown key{hint}; allowed: {', '.join(allowed) or 'none'}{note}")


def _nodes(values: dict[str, Any]) -> list[tuple[str, str, dict[str, Any]]]:
    """(key, group, node) of every component node, each a mapping with a `_target_`."""
    found = [(k, k, values.get(k)) for k in NODES if k != "scheduler" or values.get(k) is not None]
    for group in COLLECTIONS:
        if not isinstance(entries := values.get(group) or {}, dict):
            raise ConfigError(group, f"must be a mapping of names to nodes, got {entries!r}")
        found += [(f"{group}.{name}", group, node) for name, node in entries.items()]
    for key, _, node in found:
        if not isinstance(node, dict) or "_target_" not in node:
            drop = f" (to drop it: ~{key})" if node is None and "." in key else ""
            raise ConfigError(key, f"must be a mapping with a _target_{drop}, got {node!r}")
    return found


@cache
def arguments(target: str, group: str) -> tuple | None:
    """What a node of `target` may set in `group`, less what rotlearn passes (None: unchecked):
    a component's arguments (`**kwargs` followed to its bases), a library class's own, and where
    `**kwargs` go to another class (`KWARGS_TO`) that class's arguments too."""
    if target in KWARGS_TO or (not is_marked(target) and target.startswith(LIBRARIES)):
        found = parameters(target, bases=False)
        if found and found[1]:
            extra = arguments(KWARGS_TO[target], group) if target in KWARGS_TO else None
            found = (found[0] + extra, False) if extra is not None else None
    else:
        found = parameters(target) if is_marked(target) else None
    kept = [p for p in found[0] if p.name not in SUPPLIED.get(group, ())] if found else None
    return None if kept is None else tuple({p.name: p for p in reversed(kept)}.values())[::-1]


def data_paths(node: dict[str, Any]) -> list[tuple[str, Path]]:
    """(config key, path) of what a data node's root holds: the root, then its `layout`, those of
    one value together, in the order the values first appear (a KITTI sequence's frames, then
    its poses; the training sequences as listed, then the others)."""
    if "root" not in node:
        return []
    root, found, first = Path(str(node["root"])), [], {}
    for template in class_attribute(node["_target_"], "layout") or []:
        key, value, path = _CONDITION.fullmatch(template).groups()
        fields = [f for _, f, _, _ in string.Formatter().parse(path) if f]
        choices = [node[f] if isinstance(node[f], list) else [node[f]] for f in fields]
        if any(not _PLAIN.fullmatch(str(c)) for choice in choices for c in choice):
            continue  # a name that is no plain folder name: the datamodule refuses it itself
        for chosen in itertools.product(*choices) if not key or str(node.get(key)) == value else ():
            where = f"data.{fields[0]}" if fields else "data.root"
            path_of = root / path.format(**dict(zip(fields, chosen, strict=True)))
            group = first.setdefault(tuple(map(str, chosen[:1])), len(first))
            found.append((group, len(found), where, path_of))
    return [("data.root", root), *((where, path) for *_, where, path in sorted(found))]


def check_keys(values: dict[str, Any]) -> None:
    """Pass 1, from files alone: top-level keys, each node's keys and required arguments, what
    its component needs of other nodes (`config_needs`), the data root and its layout."""
    top = sorted([*TOP_LEVEL, *NODES, *COLLECTIONS])
    unknown = [k for k in values if k not in top][:1]
    owners = [f"{node}.{k}" for k in unknown for node in NODES
              if isinstance(values.get(node), dict) and k in values[node]]  # fmt: skip
    refuse_unknown("", list(values), top, elsewhere=" or ".join(owners))
    for name in (n for n in ("seed", "paths") if n not in values):
        raise ConfigError(name, "is missing")
    refuse_unknown("paths", list(values["paths"] or {}), ["output_dir"])
    for key, group, node in _nodes(values):
        if (allowed := arguments(node["_target_"], group)) is None:
            continue
        refuse_unknown(key, [k for k in node if k not in HYDRA_KEYS], [p.name for p in allowed])
        for p in (p for p in allowed if node.get(p.name, p.default) == MISSING):
            raise ConfigError(f"{key}.{p.name}", "missing (the constructor needs it)")
        needs = (
            class_attribute(node["_target_"], "config_needs")
            if is_marked(node["_target_"])
            else None
        )
        for other, protocol, what in needs or ():
            if not provides(target := (values.get(other) or {}).get("_target_", ""), protocol):
                raise ConfigError(
                    key, f"needs {what}; this run's {other} is {target.rpartition('.')[2]}"
                )
    if not (paths := data_paths(values["data"])):
        return
    (_, root), needed = paths[0], paths[1:]

    def listed(found: list[tuple[str, Path]]) -> str:  # the first four, under the root
        names = list(dict.fromkeys(str(path.relative_to(root)) for _, path in found))
        return ", ".join(names[:4]) + (f" and {len(names) - 4} more" if len(names) > 4 else "")

    if not root.is_dir():
        expected = f"; it must hold {listed(needed)} (data/README.md)" if needed else ""
        raise ConfigError("data.root", f"no directory {root}{expected}{_demo_hint(root)}")
    if missing := [(key, path) for key, path in needed if not path.exists()]:
        key = "data.root" if len(missing) == len(needed) > 1 else missing[0][0]  # none: the root
        raise ConfigError(key, f"{root} lacks {listed(missing)} (data/README.md)")


def _demo_hint(root: Path) -> str:
    """ "; make it: rotlearn-make-demo-data ..." where `root` is where a demo dataset goes
    (`<out>/demo/<name>`, with a `write_demo` in rotlearn.data.demo.<name>, read from its source
    as `rotlearn-make-demo-data` finds its writers), else ""."""
    name = root.name
    if root.parent.name != "demo" or not name.isidentifier():
        return ""
    if parameters(f"rotlearn.data.demo.{name}.write_demo") is None:
        return ""
    return f"; make it: rotlearn-make-demo-data --out {root.parent} --only {name}"


@cache
def library_constraints() -> dict[str, dict[str, Any]]:
    """What rotlearn requires of library classes' arguments beyond their annotations, per group
    or `_target_` (a description says what is expected where a union's messages would not)."""
    from pydantic import AfterValidator, Field

    pos, nonneg = Annotated[float, Gt(0)], Annotated[float, Ge(0)]
    count, index = Annotated[int, Gt(0)], Annotated[int, Ge(0)]

    def registered(kind: str) -> Any:
        def check(name: str) -> str:
            if name == "auto":  # the default, without importing Lightning (seconds)
                return name
            from lightning.pytorch.accelerators import AcceleratorRegistry as Accelerators
            from lightning.pytorch.strategies import StrategyRegistry as Strategies

            known = sorted({"auto", *(["gpu", *Accelerators] if "acc" in kind else Strategies)})
            if name not in known:
                raise ValueError(
                    f"should be the name of {kind} Lightning knows: {', '.join(known)}"
                )
            return name

        return Annotated[str, AfterValidator(check)]

    limit = Annotated[
        index | Annotated[float, Ge(0), Le(1)] | None,
        Field(description="an integer >= 0, a fraction in [0, 1], or null"),
    ]
    devices = Literal[-1, "auto"] | count | Annotated[str, Field(pattern=r"^\d+(,\d+)*,?$")]
    return {
        "optim": {"lr": pos, "weight_decay": nonneg, "eps": nonneg, "momentum": nonneg,
                  "betas": Annotated[list[Annotated[float, Ge(0), Lt(1)]], Len(2, 2)]},
        "scheduler": {"step_size": count, "T_max": count, "gamma": pos},
        "trainer": {
            "max_epochs": Annotated[count, Field(description="a positive integer (Lightning "
                                    "reads -1 as 'train forever', 0 as no training)")],
            "devices": Annotated[devices | Annotated[list[index], MinLen(1)], Field(
                description="a positive integer, -1 (every device), 'auto', or device indices")],
            "accelerator": registered("an accelerator"), "strategy": registered("a strategy"),
            "num_nodes": count, "accumulate_grad_batches": count, "min_epochs": index | None,
            "log_every_n_steps": count | None, "check_val_every_n_epoch": count | None,
            "reload_dataloaders_every_n_epochs": index, "gradient_clip_val": nonneg | None,
            "gradient_clip_algorithm": Literal["norm", "value"] | None,
            **{f"limit_{s}_batches": limit for s in ("train", "val", "test", "predict")},
            "fast_dev_run": Annotated[bool | index, Field(description="true, false or a number "
                                      "of batches >= 0")],
            "num_sanity_val_steps": Annotated[Annotated[int, Ge(-1)] | None, Field(
                description="an integer >= -1 (-1: every validation batch) or null")],
        },
        "lightning.pytorch.callbacks.ModelCheckpoint": {
            "mode": Literal["min", "max"], "save_top_k": Annotated[int, Ge(-1)],
            "every_n_epochs": index | None, "every_n_train_steps": index | None,
        },
    }  # fmt: skip


def _annotation(p: Parameter) -> Any:
    """The annotation of argument `p` from its source text, constraints included, where it names
    only builtins and what its module imports from typing modules and annotated-types (nothing
    else is imported, so a value it refuses is answered at once); unannotated, the type of its
    default (bool, a number, str) or any; None where it names anything else
    (`_imported_annotation`)."""
    if p.annotation is None:
        kind = type(p.default) if p.default != MISSING else object
        return bool if kind is bool else {int: float, float: float, str: str}.get(kind, Any)
    try:  # with the names its module imports from the typing modules (`typing_names`)
        annotation = eval(p.annotation, {}, typing_names(p.owner.rpartition(".")[0]))
    except NameError:
        return None
    return None if isinstance(annotation, str) else annotation  # "Foo": for the import to say


def _imported_annotation(owner: str, name: str) -> Any:
    """The annotation of argument `name` of `owner` (a class: of its `__init__`), imported;
    a name it uses that its module imports for type checkers only: any value."""
    from hydra.utils import get_object

    function = get_object(owner)
    function = inspect.unwrap(function.__init__ if inspect.isclass(function) else function)
    annotation = inspect.signature(function).parameters[name].annotation
    if not isinstance(annotation, str):
        return annotation
    try:  # constraint names are imported for type checkers only (`typing_names` reads those)
        return eval(annotation, function.__globals__, typing_names(owner.rpartition(".")[0]))
    except NameError:
        return Any


@cache
def _adapter(annotation: Any):
    """A strict pydantic validator of `annotation`; a mapping with a `_target_` passes (Hydra
    builds it into what the annotation asks for), a list passes as a tuple (YAML's way to write
    one: `betas: [0.9, 0.99]`), a float never passes as an integer."""
    from pydantic import ConfigDict, TypeAdapter, ValidationError, WrapValidator

    def nested(value: Any, handler: Any) -> Any:
        if isinstance(value, dict) and "_target_" in value:
            return value
        try:
            result = handler(value)
        except ValidationError as error:  # a list where a tuple is asked: checked as that tuple
            tuple_asked = any(e["type"] == "tuple_type" for e in error.errors())
            if not (isinstance(value, list) and tuple_asked):
                raise
            result = handler(tuple(value))
        if isinstance(value, float) and type(result) is int:  # 32.0 for Literal[32]
            raise ValueError(f"should be an integer, not {value!r}")
        return result

    try:
        config = ConfigDict(strict=True, arbitrary_types_allowed=True)
        return TypeAdapter(Annotated[annotation, WrapValidator(nested)], config=config)
    except TypeError:  # a type pydantic cannot check (PydanticSchemaGenerationError): any value
        return TypeAdapter(Any)


def _check(key: str, value: Any, annotation: Any) -> None:
    """`ConfigError` on `key` unless `value` fits `annotation`, saying what was expected."""
    from pydantic import ValidationError
    from pydantic.fields import FieldInfo

    try:
        _adapter(annotation).validate_python(value)
    except ValidationError as exc:
        for meta in getattr(annotation, "__metadata__", ()):  # what a union means, in words
            if isinstance(meta, FieldInfo) and meta.description:
                raise ConfigError(key, f"must be {meta.description}, got {value!r}") from None
        said = []
        for error in exc.errors(include_url=False):  # "Input should be ...", "List should have"
            text = validation_words(error["msg"])
            at = "".join(f"[{i}]" for i in error["loc"] if isinstance(i, int))
            said.append(text.replace(" after validation", "") + (f" (at {at})" if at else ""))
        whole = isinstance(value, dict) and value and all(str(k).isdigit() for k in value)
        hint = f"; a list the config does not hold yet is set whole: {key}=[...]" if whole else ""
        raise ConfigError(key, f"{' or '.join(dict.fromkeys(said))}, got {value!r}{hint}") from None


def check_values(*configs: dict[str, Any]) -> None:
    """Pass 2, importing only what each check needs, the fastest first (over all `configs`, a
    sweep's jobs: a bad value of any is answered as soon as its kind of check runs): the values
    whose annotations their source tells, the report layout, the head and the loss built, the
    calibration rule, then the values whose annotations need their component imported."""
    later = [_check_from_source(values) for values in configs]
    for values in configs:
        _check_built(values)
    for key, value, p in itertools.chain.from_iterable(later):  # these import Lightning (seconds)
        _check(key, value, _imported_annotation(p.owner, p.name))


def _check_from_source(values: dict[str, Any]) -> list[tuple[str, Any, Parameter]]:
    """`check_values`' first step for one config; returns (key, value, argument) of the values
    whose annotations need their component imported."""
    for name in (n for n in TOP_LEVEL if n in values):
        _check(name, values[name], TOP_LEVEL[name])
    if values.get("report"):  # the report a sweep writes when it ends: checked before it starts
        from rotlearn.report.layout import report_layout

        report_layout(values["report"])
    later = []
    for key, group, node in _nodes(values):
        target = node["_target_"]
        found = {p.name: p for p in arguments(target, group) or ()}
        narrowed = library_constraints().get(group, {}) | library_constraints().get(target, {})
        for name, value in node.items():
            if name in found and not (isinstance(value, dict) and "_target_" in value):
                if (annotation := narrowed.get(name) or _annotation(found[name])) is None:
                    later.append((f"{key}.{name}", value, found[name]))
                else:
                    _check(f"{key}.{name}", value, annotation)
    return later


def _check_built(values: dict[str, Any]) -> None:
    """`check_values`' second step for one config: the head and the loss built (stateless and
    cheap; the head registry checks name and size, a likelihood loss its head), and the
    calibration rule (`temperature_refusal`, before Lightning is imported)."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    built = {}
    for key in ("rep", "loss"):
        try:
            built[key] = instantiate(values[key])
        except InstantiationException as exc:  # Hydra wraps what the constructor raised
            if isinstance(exc.__cause__, ConfigError):
                raise exc.__cause__.within(key) from None
            raise
    from rotlearn.bingham.temperature import temperature_refusal  # the head's rule: no Lightning

    head = built["rep"] if "head" in values["model"] else None
    if values.get("calibrate") is True and (why := temperature_refusal(head, values["model"])):
        raise ConfigError("calibrate", why)
