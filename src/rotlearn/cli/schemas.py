"""Config validation: every node of a composed config is checked before anything is built.

rotlearn's own components (`rep`, `data`, `loss`, `callbacks.ood`) have dataclass schemas here
(a test holds their fields and defaults to their constructors' signatures); the library classes
(`optim`, `scheduler`, `trainer`, `logger.*`, `callbacks.*`) and the nets are read from their
signatures (`rotlearn.cli.signatures`); the top-level keys are in `TOP_LEVEL`. `validate(cfg)`
stops a misspelt key or a bad value at once with the full key, what was expected and the
allowed keys. A node whose `_target_` is not known here (a user's own class) is left to its
constructor.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, Literal, get_args, get_origin

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException, ValidationError

from rotlearn.cli.signatures import (
    HYDRA_KEYS,
    ConfigError,
    accepts,
    check_keys,
    check_values,
    describe,
    targets,
)
from rotlearn.errors import ConfigValueError
from rotlearn.heads import make_head

__all__ = ["SCHEMAS", "TOP_LEVEL", "ConfigError", "validate"]


@dataclass
class RepConfig:
    """`rep=`: a representation head from the registry (`rotlearn.heads.HEADS`)."""

    _target_: str = "rotlearn.heads.make_head"
    name: str = "a"
    out_dim: int = 10
    solver: str | None = None  # the A head's eigensolver: fast or eigh


@dataclass
class SyntheticWahbaConfig:
    """`data=synthetic` / `data=tiny`: `rotlearn.data.SyntheticWahbaDataModule`."""

    _target_: str = "rotlearn.data.SyntheticWahbaDataModule"
    phi_max_deg: float = 180.0
    sigma: float = 0.01
    num_matches: int = 100
    batch_size: int = 100
    batches_per_epoch: int = 5
    num_val: int = 100
    num_test: int = 500
    eval_batch_size: int = 100
    redraw_test: bool = False
    seed: int = 0


@dataclass
class ShapeNetConfig:
    """`data=shapenet`: `rotlearn.data.ShapeNetDataModule`."""

    _target_: str = "rotlearn.data.ShapeNetDataModule"
    root: str = "data/shapenet"
    format: str = "pts"
    synset: str = "02691156"
    num_train: int = 2290
    num_test: int = 400
    point_fraction: float = 0.5
    num_points: int = 1024
    rotations_per_cloud: int = 10
    iterations_per_epoch: int = 200
    test_rotations: int = 100
    num_val: int = 20
    seed: int = 0
    cache_dir: str | None = None


@dataclass
class ImagePairConfig:
    """Keys shared by the image-pair datamodules (`rotlearn.data.ImagePairDataModule`)."""

    batch_size: int = 32
    eval_batch_size: int = 64
    num_workers: int = 2
    corrupt_fraction: float = 0.0
    num_val: int = 64
    mean: float = 0.0
    std: float = 1.0
    seed: int = 0
    cache_dir: str | None = None


@dataclass
class KittiConfig(ImagePairConfig):
    """`data=kitti`: `rotlearn.data.KittiOdometryDataModule`."""

    _target_: str = "rotlearn.data.KittiOdometryDataModule"
    root: str = "data/kitti"
    train_sequences: list[str] = field(
        default_factory=lambda: ["00", "02", "05", "06", "07", "08", "09", "10"]
    )
    test_sequences: list[str] = field(default_factory=lambda: ["00"])
    camera: str = "image_2"
    delta: int = 1
    image_size: int = 224
    pair_channels: int = 6


@dataclass
class MAVConfig(ImagePairConfig):
    """`data=mav`: `rotlearn.data.MAVDataModule`."""

    _target_: str = "rotlearn.data.MAVDataModule"
    root: str = "data/mav"
    train_scenes: list[str] = field(default_factory=lambda: ["outdoor"])
    test_scenes: list[str] = field(default_factory=lambda: ["outdoor"])
    test_fraction: float = 0.1
    pose_tolerance_ms: float = 30.0
    resize: int = 256
    image_size: int = 224
    pair_channels: int = 2
    mean: float = 0.45
    std: float = 0.25


@dataclass
class ChordalLossConfig:
    _target_: str = "rotlearn.losses.ChordalLoss"


@dataclass
class AngularLossConfig:
    _target_: str = "rotlearn.losses.AngularLoss"


@dataclass
class BinghamLossConfig:
    """`loss=bingham`: `rotlearn.losses.BinghamNLLLoss`; `rep` is interpolated from `rep.name`."""

    _target_: str = "rotlearn.losses.BinghamNLLLoss"
    rep: str | None = None


@dataclass
class OODConfig:
    """`callbacks=ood`: `rotlearn.ood.OODEvaluation` (conf/callbacks/ood.yaml)."""

    _target_: str = "rotlearn.ood.OODEvaluation"
    quantiles: list[float] = field(default_factory=lambda: [0.25, 0.5, 0.75, 1.0])
    scores: list[str] = field(default_factory=lambda: ["dt", "eigengap", "raw_norm", "autoencoder"])
    autoencoder_ckpt: str | None = None
    autoencoder_train: dict[str, Any] | None = None
    corrupt_fraction: float = 0.5
    table: dict[str, float] | None = None
    noise_pairs: int = 64
    unseen_scenes_ood: bool = False
    max_train_pairs: int | None = None


SCHEMAS: dict[str, dict[str, type]] = {
    "rep": {RepConfig._target_: RepConfig},
    "data": {c._target_: c for c in (SyntheticWahbaConfig, ShapeNetConfig, KittiConfig, MAVConfig)},
    "loss": {c._target_: c for c in (ChordalLossConfig, AngularLossConfig, BinghamLossConfig)},
    "callbacks.ood": {OODConfig._target_: OODConfig},
}
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
    "float32_matmul_precision": Literal["highest", "high", "medium"],
    "trial": int,
    "trials": int,
    "sweep_seed": int,
    "lr_range": tuple[float, float],
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
        raise ConfigError(f"config key {key}: cannot be resolved: {reason}") from None
    return value


def _mapping(cfg: DictConfig, key: str) -> dict[str, Any] | None:
    """The node at `key` as a resolved dict with a `_target_` (None where absent and optional)."""
    node = OmegaConf.select(cfg, key)
    if node is None and key in OPTIONAL:
        return None
    if node is None:
        raise ConfigError(f"config key {key} is missing")
    if not isinstance(node, DictConfig) or "_target_" not in node:
        raise ConfigError(f"config key {key} must be a mapping with a _target_, got {node!r}")
    for name in node:
        _resolved(cfg, f"{key}.{name}")  # names the key whose interpolation fails
    return OmegaConf.to_container(node, resolve=True)


def _check_dataclass(cfg: DictConfig, key: str, schema: type) -> None:
    node = OmegaConf.select(cfg, key)
    check_keys(key, node, [f.name for f in fields(schema)])
    try:
        OmegaConf.merge(OmegaConf.structured(schema), node)
    except ValidationError as exc:
        field_ = next(f for f in fields(schema) if f.name == exc.key)
        value = OmegaConf.to_container(node, resolve=True)[exc.key]
        raise ConfigError(
            f"config key {key}.{exc.key}: expected {field_.type}, got {value!r}"
        ) from None


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
    )  # callbacks.<any name> with OODEvaluation's _target_ is checked by OODConfig
    if schema is not None:
        _check_dataclass(cfg, key, schema)
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
        raise ConfigError(f"config key {key} must be a mapping of names to nodes, got {node!r}")
    for name in node:
        if OmegaConf.select(node, str(name)) is None:
            raise ConfigError(
                f"config key {key}.{name}: must be a mapping with a _target_, got None "
                f"(to drop it: ~{key}.{name})"
            )
        _check_node(cfg, f"{key}.{name}", group=key)


def _check_top_level(cfg: DictConfig) -> None:
    check_keys("", [k for k in cfg if k != "hydra"], sorted([*TOP_LEVEL, *NODES, "paths"]))
    for name in REQUIRED:
        if name not in cfg:
            raise ConfigError(f"config key {name} is missing")
    for name, annotation in TOP_LEVEL.items():
        if name in cfg and not accepts(value := _resolved(cfg, name), annotation):
            if get_origin(annotation) is Literal:
                *first, last = map(repr, get_args(annotation))
                expected = f"must be {', '.join(first)} or {last}"
            else:
                expected = f"expected {describe(annotation)}"
            raise ConfigError(f"config key {name}: {expected}, got {value!r}")
    for name, (low, high) in BOUNDS.items():
        if name in cfg and not low <= (value := _resolved(cfg, name)) <= high:
            raise ConfigError(f"config key {name}: must lie in [{low}, {high}], got {value!r}")
    paths = _resolved(cfg, "paths")
    if not isinstance(paths, dict):
        raise ConfigError(f"config key paths: must be a mapping with output_dir, got {paths!r}")
    check_keys("paths", paths, list(PATHS))
    for name, annotation in PATHS.items():
        if not accepts(value := paths.get(name), annotation) or not value:
            raise ConfigError(
                f"config key paths.{name}: expected a non-empty {describe(annotation)}, "
                f"got {value!r}"
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
        make_head(cfg.rep.name, cfg.rep.out_dim, cfg.rep.get("solver"))
    except ConfigValueError as exc:
        raise ConfigError(f"config key rep.{exc.key}: {exc.message}") from None
