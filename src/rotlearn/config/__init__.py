"""Floor 4: a run's config composed, validated and built, from a command line, a notebook or a test.

    from rotlearn.config import build, compose

    cfg = compose(["rep=a", "loss=bingham", "data=tiny"])  # conf/train.yaml + overrides, validated
    model, datamodule = build(cfg)  # the LightningModule and LightningDataModule, not yet trained

`compose` is Hydra's compose API with rotlearn's answers to the usual mistakes: an unknown option
(`rep=aa`: the real options and the nearest one) and an unknown key (`optim.lrr=1e-3`, with or
without `+`: the nearest known key and the allowed ones, instead of Hydra's advice to append it).
A key that a component takes but its YAML does not list is set without `+`, as the others are.
`validate` checks every node against its constructor (`rotlearn.config.checks`); `build` validates,
seeds and instantiates. `rotlearn-train` and `rotlearn-eval` run the same `command_line` check
before Hydra starts, so a refused command writes nothing. A plain `hydra.compose` on conf/ works
too: the component schemas its YAML files start from register themselves
(`rotlearn.config.store`).

Why pydantic (a `TypeAdapter` per argument, strict mode) rather than hydra-zen: the constraints
live on the constructors' own signatures as `Annotated[int, Gt(0)]` (annotated-types, the
metadata pydantic reads), the YAML files stay the configs, and one adapter per annotation checks
`Literal`s, unions, nested lists and bounds with messages that name the expected value. hydra-zen
would generate dataclass configs from the same signatures and validate them with pydantic when a
node is instantiated, i.e. after the run has started; here nothing is built before every value is
known to be right, and no second config representation is needed.
"""

from __future__ import annotations

import difflib
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rotlearn.extras import require

require("train", "rotlearn.config")

from hydra.errors import ConfigCompositionException, MissingConfigException  # noqa: E402
from omegaconf import DictConfig, OmegaConf, open_dict  # noqa: E402

from rotlearn.config.checks import check_keys, check_values, plain  # noqa: E402
from rotlearn.config.store import register_schemas  # noqa: E402
from rotlearn.errors import ConfigError  # noqa: E402
from rotlearn.paths import config_dir  # noqa: E402

if TYPE_CHECKING:
    import lightning.pytorch as pl

__all__ = ["ConfigError", "build", "command_line", "compose", "options", "validate"]

_ABSENT = object()


def options(group: str, root: Path | None = None) -> list[str]:
    """The options of a config group: the names of conf/<group>/*.yaml."""
    return sorted(p.stem for p in Path(root or config_dir()).joinpath(group).glob("*.yaml"))


def _parse(overrides: Sequence[str]) -> list[Any]:
    from hydra.core.override_parser.overrides_parser import OverridesParser

    return OverridesParser.create().parse_overrides(list(overrides))


def _unknown_option(exc: MissingConfigException, overrides: Sequence[str], root: Path) -> None:
    """A `group=option` of the command line that names no file: ConfigError with the options."""
    group, _, option = str(exc.missing_cfg_file).rpartition("/")
    named = {(o.key_or_group.lstrip("/"), str(o.value())) for o in _parse(overrides)}
    if not group or (group, option) not in named:
        return
    real = options(group, root)
    near = difflib.get_close_matches(option, real, n=1, cutoff=0.5)
    hint = f"; did you mean {group}={near[0]}?" if near else ""
    raise ConfigError(group, f"no option {option!r}{hint}; options: {', '.join(real)}") from None


def _with_appends(overrides: Sequence[str], base: DictConfig, root: Path) -> list[str]:
    """`overrides` with a `+` before each plain `key=value` whose key `base` lacks: an argument
    its YAML does not list is set like the others, and a misspelt key reaches `validate`."""
    from hydra.core.override_parser.types import OverrideType

    raw = OmegaConf.to_container(base, resolve=False)
    out = []
    for override in _parse(overrides):
        key = override.key_or_group
        node = raw
        for part in key.split("."):
            node = node.get(part, _ABSENT) if isinstance(node, dict) else _ABSENT
        plain_value = override.type == OverrideType.CHANGE and not root.joinpath(key).is_dir()
        absent = node is _ABSENT
        out.append(f"+{override.input_line}" if plain_value and absent else override.input_line)
    return out


def _compose(name: str, overrides: Sequence[str], root: Path) -> tuple[DictConfig, list[str]]:
    """Hydra's compose (with its `hydra` node) of `overrides` and the overrides it took."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.override_parser.types import OverrideType

    register_schemas()
    overrides = list(overrides)
    with initialize_config_dir(config_dir=str(root), version_base="1.3"):
        try:
            try:
                return hydra_compose(name, overrides, return_hydra_config=True), overrides
            except ConfigCompositionException as exc:
                if isinstance(exc, MissingConfigException):
                    raise
                structure = [  # options and additions: what the values are set in
                    o.input_line
                    for o in _parse(overrides)
                    if o.type != OverrideType.CHANGE or root.joinpath(o.key_or_group).is_dir()
                ]
                base = hydra_compose(name, structure, return_hydra_config=True)
                fixed = _with_appends(overrides, base, root)
                if fixed == overrides:
                    raise
                return hydra_compose(name, fixed, return_hydra_config=True), fixed
        except MissingConfigException as exc:
            _unknown_option(exc, overrides, root)
            raise


def _is_hydras(override: str) -> bool:
    return override.lstrip("+~").startswith(("hydra.", "hydra/"))


def compose(
    overrides: Sequence[str] = (),
    *,
    output_dir: str | Path | None = None,
    config_name: str = "train",
    root: str | Path | None = None,
    check: bool = True,
) -> DictConfig:
    """The config of conf/<config_name>.yaml with `overrides`, as `rotlearn-train` composes it.

    Args:
        overrides: command-line overrides, e.g. ["rep=a", "optim.lr=1e-3"] (Hydra's own keys,
            `hydra.*`, are left out).
        output_dir: `paths.output_dir`, where a run of it would write (default: the run
            directory `rotlearn-train` would make, `outputs/runs/<time>`; nothing is written).
        config_name: the primary config (conf/train.yaml).
        root: the config directory (default: rotlearn's conf/).
        check: validate it (`validate`); False returns it as composed.

    Raises:
        ConfigError: an unknown option or key, or a value its component refuses (naming it).
    """
    root = Path(root or config_dir())
    kept = [o for o in overrides if not _is_hydras(o)]
    cfg, _ = _compose(config_name, kept, root)
    run_dir = OmegaConf.select(cfg, "hydra.run.dir", default=None)
    with open_dict(cfg):
        del cfg["hydra"]
        if output_dir is not None or OmegaConf.is_interpolation(cfg.get("paths", {}), "output_dir"):
            cfg.paths.output_dir = str(output_dir if output_dir is not None else run_dir)
    if check:
        validate(cfg)
    return cfg


def command_line(
    args: Sequence[str], output_dir: str = "new-run", config_name: str = "train", check: bool = True
) -> list[str]:
    """Validate the config a command line composes to, before Hydra starts and writes anything;
    returns the arguments for Hydra (with `+` before each component argument its YAML does not
    list). A sweep (-m) is checked with the first value of each swept key; `check=False` only
    composes (another primary config than train's).

    Raises:
        ConfigError: naming the option or key at fault.
        hydra.errors.HydraException, omegaconf.errors.OmegaConfBaseException: it does not compose
            (left for Hydra to report).
    """
    flags = [a for a in args if a.startswith("-")]
    overrides = [a for a in args if not a.startswith("-") and not _is_hydras(a)]
    first = []
    for override in _parse(overrides):
        if override.is_sweep_override():
            values = list(override.sweep_string_iterator())
            first.append(f"{override.get_key_element()}={values[0]}")
        else:
            first.append(override.input_line)
    root = config_dir()
    cfg, taken = _compose(config_name, first, root)
    with open_dict(cfg):
        del cfg["hydra"]
        cfg.paths.output_dir = output_dir
    if check:
        validate(cfg)
    added = {o.lstrip("+").split("=", 1)[0] for o in taken if o.startswith("+")}
    fixed = [f"+{a}" if not a.startswith(("+", "~")) and a.split("=", 1)[0] in added else a
             for a in overrides]  # fmt: skip
    hydras = [a for a in args if not a.startswith("-") and _is_hydras(a)]
    return [*flags, *fixed, *hydras]


def validate(cfg: DictConfig) -> None:
    """Check every key and value of a composed train config (`rotlearn.config.checks`): first
    what files alone tell (unknown keys, required arguments, data folders), then each value
    against its constructor's annotation and the rules that span keys. Builds nothing but the
    head and the loss (stateless, cheap).

    Raises:
        ConfigError: naming the full key, and what was expected or the allowed keys.
    """
    values = plain(cfg)
    check_keys(values)
    check_values(values)


def _instantiate(cfg: DictConfig, key: str) -> Any:
    """Instantiate the node `key`; a component's `ConfigError` (its key relative to the node)
    comes back with the full key (for the model: the group a `${group}` part comes from)."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    try:
        return instantiate(cfg[key])
    except InstantiationException as exc:
        cause = exc.__cause__
        if not isinstance(cause, ConfigError):
            raise
        part = cause.key.split(".")[0]
        raw = OmegaConf.to_container(cfg[key], resolve=False).get(part)
        if isinstance(raw, str) and raw.startswith("${") and raw.endswith("}"):
            raise ConfigError(f"{raw[2:-1]}{cause.key[len(part):]}", cause.message) from None
        raise cause.within(key) from None


def build(cfg: DictConfig) -> tuple[pl.LightningModule, pl.LightningDataModule]:
    """The model and datamodule of a composed train config: validated, seeded with `cfg.seed`,
    `instantiate(cfg.data)` and `instantiate(cfg.model)` (the regressor with its net, head, loss
    and optimizer from their groups, or the auto-encoder). The model keeps the resolved config
    (`run_config`) for its checkpoints.

    Raises:
        ConfigError: see `validate`.
    """
    import lightning.pytorch as pl

    validate(cfg)
    pl.seed_everything(cfg.seed, workers=True, verbose=False)
    datamodule = _instantiate(cfg, "data")
    model = _instantiate(cfg, "model")
    model.run_config = plain(cfg)
    return model, datamodule
