"""Structured-config schemas (dataclasses) for the `rep`, `data` and `loss` nodes.

`validate(cfg)` checks a composed config against them before anything is built, so that a
misspelt key or a value of the wrong type stops the run at once with the full key, what was
expected and the allowed keys. A node whose `_target_` has no schema here (a user's own class)
is left to its constructor.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass, field, fields
from typing import Any

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ValidationError

from rotlearn.errors import ConfigValueError
from rotlearn.heads import make_head

__all__ = ["SCHEMAS", "ConfigError", "validate"]


class ConfigError(ValueError):
    """A config value that cannot be used; the message names its full key."""


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
    """`loss=bingham`: `rotlearn.bingham.BinghamNLLLoss`; `rep` is interpolated from `rep.name`."""

    _target_: str = "rotlearn.bingham.BinghamNLLLoss"
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
OPTIONAL = {"callbacks.ood"}  # checked when present


def _check_node(cfg: DictConfig, key: str) -> None:
    node = OmegaConf.select(cfg, key)
    if node is None and key in OPTIONAL:
        return
    if node is None:
        raise ConfigError(f"config key {key} is missing")
    if not isinstance(node, DictConfig) or "_target_" not in node:
        raise ConfigError(f"config key {key} must be a mapping with a _target_, got {node!r}")
    schema = SCHEMAS[key].get(node._target_)
    if schema is None:
        return
    allowed = [f.name for f in fields(schema)]
    for name in node:
        if name not in allowed:
            close = difflib.get_close_matches(str(name), allowed, n=1)
            hint = f" (did you mean {key}.{close[0]}?)" if close else ""
            raise ConfigError(
                f"config key {key}.{name}: unknown{hint}; allowed: {', '.join(allowed)}"
            )
    try:
        OmegaConf.merge(OmegaConf.structured(schema), node)
    except ValidationError as exc:
        field = next(f for f in fields(schema) if f.name == exc.key)
        value = OmegaConf.to_container(node, resolve=True)[exc.key]
        raise ConfigError(
            f"config key {key}.{exc.key}: expected {field.type}, got {value!r}"
        ) from None


def validate(cfg: DictConfig) -> None:
    """Check the `rep`, `data`, `loss` (and `callbacks.ood`) nodes against their schemas.

    Raises:
        ConfigError: naming the full key, and the allowed keys or the expected type.
    """
    for key in SCHEMAS:
        _check_node(cfg, key)
    if cfg.get("test_ckpt", "last") not in ("last", "best"):
        raise ConfigError(f"config key test_ckpt: must be 'last' or 'best', got {cfg.test_ckpt!r}")
    try:  # the registry knows the names and sizes; heads are stateless and cheap to make
        make_head(cfg.rep.name, cfg.rep.out_dim, cfg.rep.get("solver"))
    except ConfigValueError as exc:
        raise ConfigError(f"config key rep.{exc.key}: {exc.message}") from None
