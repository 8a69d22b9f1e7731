"""Config validation: every node of a composed config is checked before anything is built.

rotlearn's own components (`model`, `rep`, `data`, `net`, `loss`, `callbacks.ood`) have dataclass
schemas DERIVED here from their constructors' signatures (`COMPONENTS`; fields, annotations and
defaults via `rotlearn.cli.signatures.constructor_parameters`, following `**kwargs` to base
classes), so a schema cannot disagree with the code. Each schema's defaults are registered with
Hydra's ConfigStore as `<group>/<option>_schema` (e.g. `data/kitti_schema`); a YAML under conf/
starts from it in its defaults list and holds only what differs. The library classes (`optim`,
`scheduler`, `trainer`, `logger.*`, `callbacks.*`) and the nets are checked from their signatures
(`rotlearn.cli.signatures.targets`); the top-level keys are in `TOP_LEVEL`. `validate(cfg)` stops a
misspelt key or a bad value at once with the full key, what was expected and the allowed keys. A
node whose `_target_` is not known here (a user's own class) is left to its constructor.
"""

from __future__ import annotations

import dataclasses
import inspect
from functools import partial
from typing import Any, Literal, get_args, get_origin

from hydra.core.config_store import ConfigStore
from hydra.utils import get_object
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from rotlearn.cli.signatures import (
    HYDRA_KEYS,
    MISSING,
    ConfigError,
    Spec,
    accepts,
    check_keys,
    check_values,
    constructor_parameters,
    describe,
    targets,
)
from rotlearn.heads import make_head

__all__ = ["COMPONENTS", "SCHEMAS", "TOP_LEVEL", "ConfigError", "register_schemas", "validate"]

# Group -> option -> `_target_`: rotlearn's components with a derived schema. Each is registered
# in Hydra's ConfigStore as <group>/<option>_schema (the YAML's starting point).
COMPONENTS: dict[str, dict[str, str]] = {
    "rep": {"head": "rotlearn.heads.make_head"},
    "data": {
        "synthetic": "rotlearn.data.SyntheticWahbaDataModule",
        "shapenet": "rotlearn.data.ShapeNetDataModule",
        "kitti": "rotlearn.data.KittiOdometryDataModule",
        "mav": "rotlearn.data.MAVDataModule",
    },
    "net": {
        "pointnet": "rotlearn.nets.PointNet",
        "pair_cnn": "rotlearn.nets.PairCNN",
        "pair_corr": "rotlearn.nets.PairCorrelationNet",
        "autoencoder": "rotlearn.nets.ConvAutoEncoder",
    },
    "loss": {
        "chordal": "rotlearn.losses.ChordalLoss",
        "angular": "rotlearn.losses.AngularLoss",
        "bingham": "rotlearn.losses.BinghamNLLLoss",
        "fisher_nll": "rotlearn.losses.FisherNLLLoss",
    },
    "callbacks.ood": {"ood": "rotlearn.ood.OODEvaluation"},
    "model": {
        "regressor": "rotlearn.lit.RotationRegressor",
        "autoencoder": "rotlearn.lit.AutoEncoderModule",
    },
}
VALIDATED_BY_SIGNATURE = ("net",)  # checked with the library classes (`targets()["net"]`)


def _default(value: Any) -> Any:
    """A constructor default as a config value: a tuple becomes a list, none becomes `???`."""
    if value is inspect.Parameter.empty:
        return MISSING
    return list(value) if isinstance(value, tuple) else value


def schema(target: str) -> type:
    """The dataclass schema of the constructor (or function) named `target`: `_target_`, then one
    field per argument (base classes' arguments passed on with `**kwargs` included), typed by its
    annotation, with its default (a tuple as a list; a required argument: `???`)."""
    params = constructor_parameters(get_object(target))
    fields: list[tuple[str, Any, Any]] = [("_target_", str, dataclasses.field(default=target))]
    for name, (annotation, default) in params.items():
        value = _default(default)
        if isinstance(value, list | dict):
            field = dataclasses.field(default_factory=partial(type(value), value))
        else:
            field = dataclasses.field(default=value)
        fields.append((name, annotation, field))
    cls = dataclasses.make_dataclass(f"{target.rsplit('.', 1)[-1]}Schema", fields)
    cls.__doc__ = f"Config node of `{target}`, derived from its signature."
    return cls


def defaults(cls: type) -> dict[str, Any]:
    """A schema's fields and defaults as a plain mapping (types are checked by `validate`)."""
    return {
        f.name: f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        for f in dataclasses.fields(cls)
    }


def _schemas() -> dict[str, dict[str, type]]:
    made: dict[str, dict[str, type]] = {}
    for group, options in COMPONENTS.items():
        for target in dict.fromkeys(options.values()):
            made.setdefault(group, {})[target] = schema(target)
    return made


ALL_SCHEMAS = _schemas()
# Checked here (the rest by `targets()`): `_target_` -> schema, per group.
SCHEMAS: dict[str, dict[str, type]] = {
    group: found for group, found in ALL_SCHEMAS.items() if group not in VALIDATED_BY_SIGNATURE
}


def register_schemas() -> None:
    """Store each schema's defaults in Hydra's ConfigStore as `<group>/<option>_schema`, the
    first entry of that option's YAML defaults list. The node is untyped: `validate` checks
    the types, so that a wrong value is reported with its full key and what was expected."""
    store = ConfigStore.instance()
    for group, options in COMPONENTS.items():
        for option, target in options.items():
            node = OmegaConf.create(defaults(ALL_SCHEMAS[group][target]))
            store.store(group=group.replace(".", "/"), name=f"{option}_schema", node=node)


register_schemas()


OPTIONAL = {"scheduler"}  # checked when present
NODES = (
    "model",
    "rep",
    "net",
    "data",
    "loss",
    "optim",
    "scheduler",
    "trainer",
    "logger",
    "callbacks",
)

# Top-level keys (defaults in conf/train.yaml; trial, trials, sweep_seed, lr_range from sweep=lr).
TOP_LEVEL: dict[str, Any] = {
    "ckpt_path": str | None,
    "seed": int,
    "test_ckpt": Literal["last", "best"],
    "calibrate": bool | Literal["auto"],
    "float32_matmul_precision": Literal["highest", "high", "medium"],
    "trial": int,
    "trials": int,
    "sweep_seed": int,
    "lr_range": tuple[float, float],
    "report": dict | None,  # rotlearn-report's layout (an experiment's report node)
}
REQUIRED = ("seed", "paths")
BOUNDS = {"seed": (0, 2**32 - 1), "trial": (0, 2**31), "trials": (1, 2**31)}  # seed: numpy's
PATHS: dict[str, Any] = {"output_dir": str}


def _resolved(cfg: DictConfig, key: str) -> Any:
    """The value at `key` with interpolations resolved, as plain Python."""
    try:
        value = OmegaConf.select(cfg, key, throw_on_resolution_failure=True)
        if isinstance(value, DictConfig | ListConfig):
            value = OmegaConf.to_container(value, resolve=True)
    except OmegaConfBaseException as exc:
        reason = str(exc).splitlines()[0]
        raise ConfigError(key, f"cannot be resolved: {reason}") from None
    return value


def _mapping(cfg: DictConfig, key: str) -> dict[str, Any] | None:
    """The node at `key` as a resolved dict with a `_target_` (None where absent and optional)."""
    node = OmegaConf.select(cfg, key)
    if node is None and key in OPTIONAL:
        return None
    if node is None:
        raise ConfigError(key, "is missing")
    if not isinstance(node, DictConfig) or "_target_" not in node:
        raise ConfigError(key, f"must be a mapping with a _target_, got {node!r}")
    for name in node:
        _resolved(cfg, f"{key}.{name}")  # names the key whose interpolation fails
    return OmegaConf.to_container(node, resolve=True)


def _check_schema(key: str, values: dict[str, Any], schema: type) -> None:
    """Check a resolved node against a derived schema: its keys (`_target_` and the fields),
    required values, then each value against the field's annotation."""
    fields = dataclasses.fields(schema)
    check_keys(key, values, [f.name for f in fields])
    params = {f.name: (f.type, inspect.Parameter.empty if _required(f) else None) for f in fields}
    spec = Spec(get_object(values["_target_"]), params)
    check_values(key, {k: v for k, v in values.items() if k not in HYDRA_KEYS}, spec)


def _required(field: dataclasses.Field) -> bool:
    return field.default == MISSING


def _check_node(cfg: DictConfig, key: str, group: str | None = None) -> None:
    """Check the node at `key` against the dataclass schema or signature of its `_target_`."""
    values = _mapping(cfg, key)
    if values is None:
        return
    group = group or key
    schema = next(
        (
            schemas[values["_target_"]]
            for name, schemas in SCHEMAS.items()
            if (name == group or name.startswith(f"{group}.")) and values["_target_"] in schemas
        ),
        None,
    )  # callbacks.<any name> with OODEvaluation's _target_ is checked by its schema
    if schema is not None:
        _check_schema(key, values, schema)
        return
    spec = targets().get(group, {}).get(values["_target_"])
    if spec is not None:
        check_values(key, {k: v for k, v in values.items() if k not in HYDRA_KEYS}, spec)


def _check_collection(cfg: DictConfig, key: str) -> None:
    """`logger` and `callbacks`: a mapping of names to nodes, each checked by its `_target_`."""
    node = OmegaConf.select(cfg, key)
    if node is None:
        return
    if not isinstance(node, DictConfig):
        raise ConfigError(key, f"must be a mapping of names to nodes, got {node!r}")
    for name in node:
        if OmegaConf.select(node, str(name)) is None:
            raise ConfigError(
                f"{key}.{name}",
                f"must be a mapping with a _target_, got None (to drop it: ~{key}.{name})",
            )
        _check_node(cfg, f"{key}.{name}", group=key)


def _check_top_level(cfg: DictConfig) -> None:
    check_keys("", [k for k in cfg if k != "hydra"], sorted([*TOP_LEVEL, *NODES, "paths"]))
    for name in REQUIRED:
        if name not in cfg:
            raise ConfigError(name, "is missing")
    for name, annotation in TOP_LEVEL.items():
        if name in cfg and not accepts(value := _resolved(cfg, name), annotation):
            if get_origin(annotation) is Literal:
                *first, last = map(repr, get_args(annotation))
                expected = f"must be {', '.join(first)} or {last}"
            else:
                expected = f"expected {describe(annotation)}"
            raise ConfigError(name, f"{expected}, got {value!r}")
    for name, (low, high) in BOUNDS.items():
        if name in cfg and not low <= (value := _resolved(cfg, name)) <= high:
            raise ConfigError(name, f"must lie in [{low}, {high}], got {value!r}")
    paths = _resolved(cfg, "paths")
    if not isinstance(paths, dict):
        raise ConfigError("paths", f"must be a mapping with output_dir, got {paths!r}")
    check_keys("paths", paths, list(PATHS))
    for name, annotation in PATHS.items():
        if not accepts(value := paths.get(name), annotation) or not value:
            raise ConfigError(
                f"paths.{name}", f"expected a non-empty {describe(annotation)}, got {value!r}"
            )


def validate(cfg: DictConfig) -> None:
    """Check every node of a composed train config: the top-level keys, then `model`, `rep`, `net`,
    `data`, `loss`, `optim`, `scheduler` (optional), `trainer`, each `logger.*` and each
    `callbacks.*`. Nothing is built but a (stateless) head.

    Raises:
        ConfigError: naming the full key, and the allowed keys or what was expected.
    """
    _check_top_level(cfg)
    for key in ("rep", "net", "data", "loss", "optim", "scheduler", "trainer", "model"):
        _check_node(cfg, key)  # the model last: it is built from the nodes before it
    for key in ("logger", "callbacks"):
        _check_collection(cfg, key)
    try:  # the registry knows the names and sizes; heads are stateless and cheap to make
        head = make_head(cfg.rep.name, cfg.rep.out_dim, cfg.rep.get("solver"))
    except ConfigError as exc:
        raise exc.within("rep") from None
    if _resolved(cfg, "calibrate") is True and not head.defines_belief:  # before any run dir
        raise ConfigError(
            "calibrate", f"fits the temperature of a belief; rep={head.name} has none"
        )


def validate_command_line(args: list[str], output_dir: str) -> None:
    """Compose the train config of a command line (its Hydra keys left out, `paths.output_dir`
    set to `output_dir`) and `validate` it, before Hydra starts and writes anything. Does nothing
    inside a running Hydra app (there `build` validates).

    Raises:
        hydra.errors.HydraException, omegaconf.errors.OmegaConfBaseException: it does not compose.
        ConfigError: a value is invalid (naming its key).
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from rotlearn.paths import config_dir

    if GlobalHydra.instance().is_initialized():
        return
    overrides = [a for a in args if not a.lstrip("+~").startswith(("hydra.", "hydra/"))]
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("train", [*overrides, f"paths.output_dir={output_dir}"])
    validate(cfg)
