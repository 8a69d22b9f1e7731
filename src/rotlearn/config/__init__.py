"""Floor 4: a run's config composed, validated and built, from a command line, a notebook or a
test::

    from rotlearn.config import build, compose

    cfg = compose(["rep=a", "loss=bingham", "data=tiny"])  # conf/train.yaml + overrides, validated
    model, datamodule = build(cfg)  # the LightningModule and LightningDataModule, not yet trained

`compose` is Hydra's compose API with rotlearn's answer to an unknown option (`rep=aa`: the real
options and the nearest) and key (`optim.lrr=1e-3`, with or without `+`: the nearest key and the
allowed ones, `rotlearn.config.checks`); an argument a component takes is set without `+` even
where its YAML does not list it. The commands check their command line the same way before Hydra
starts (`command_line`: rotlearn-train, with a sweep's other values; `command_line_config`, then
`validate`: rotlearn-eval and a resume), so a refused command writes nothing. Each YAML starts
from its component's defaults: `schema/` + its target in Hydra's ConfigStore
(`register_schemas`, which rotlearn's Hydra plugin runs wherever Hydra composes, so a plain
`hydra.compose` on conf/ works; the configs' resolvers, `${rl.loguniform:...}` and
`${rl.gpu_precision:}`, register with this module: `rotlearn.config.resolvers`).

Why pydantic (a strict `TypeAdapter` per argument) rather than hydra-zen: the constraints live on
the constructors' own signatures as annotated-types metadata (`Annotated[int, Gt(0)]`), which
pydantic reads as they are, the YAML files stay the configs, and an adapter checks `Literal`s,
unions, nested lists and bounds with messages that say what was expected. hydra-zen would generate
a second, dataclass representation of the same signatures and check it with pydantic when a node
is instantiated, i.e. once the run has started; here every value is checked before anything is
built or written.
"""

from __future__ import annotations

import difflib
import itertools
import math
from collections.abc import Callable, Sequence
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rotlearn.extras import require

require("train", "rotlearn.config")

from hydra.errors import ConfigCompositionException, MissingConfigException  # noqa: E402
from omegaconf import DictConfig, OmegaConf, open_dict  # noqa: E402

from rotlearn.config import resolvers  # noqa: E402, F401  (registers `${rl.*:...}`)
from rotlearn.config.checks import (  # noqa: E402
    COLLECTIONS,
    arguments,
    check_keys,
    check_values,
    plain,
    refuse_unknown,
)
from rotlearn.config.source import NOT_LITERAL, marked, parameters  # noqa: E402
from rotlearn.errors import ConfigError  # noqa: E402
from rotlearn.paths import config_dir  # noqa: E402
from rotlearn.report.identity import is_hydra_key  # noqa: E402

if TYPE_CHECKING:
    import lightning.pytorch as pl

__all__ = [
    "ConfigError",
    "build",
    "command_line",
    "command_line_config",
    "compose",
    "grammar_reason",
    "register_schemas",
    "sweep_values",
    "validate",
]

CHECKED_JOBS = 16  # a sweep of at most this many jobs is validated job by job before it starts


def schema(target: str) -> dict[str, Any]:
    """The defaults node of a component: `_target_` and each argument's default (`???` where
    required), read from its source (`rotlearn.config.source`).

    Raises:
        ValueError: a default that is no literal (a YAML value cannot hold it).
    """
    found = parameters(target)[0]
    for p in (p for p in found if p.default is NOT_LITERAL):
        raise ValueError(f"{target}: the default of {p.name} is no literal; a component's "
                         "defaults must be YAML values")  # fmt: skip
    return {"_target_": target, **{p.name: p.default for p in found}}


@cache
def register_schemas() -> tuple[str, ...]:
    """Store `schema/` + the dotted name where it is defined in Hydra's ConfigStore, for every
    component marked `@config_target` (once per process); returns their names."""
    from hydra.core.config_store import ConfigStore

    for target in marked():
        ConfigStore.instance().store(group="schema", name=target, node=schema(target))
    return marked()


def grammar_reason(error: Exception, text: str) -> str:
    """Why Hydra's override grammar could not read `text`, in a few words: the first line of
    its error ("no viable alternative at input '[1'"), without its "expecting ..." list."""
    said = str(error).removeprefix(f"Error parsing override '{text}'")
    lines = [line.strip() for line in said.splitlines() if line.strip()]
    return lines[0].split(" expecting ")[0] if lines else "not Hydra's override grammar"


def _parse(overrides: Sequence[str]) -> list[Any]:
    """Hydra's parse of each override; `ConfigError` names one its grammar cannot read."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parser = OverridesParser.create()
    try:
        return parser.parse_overrides(list(overrides))
    except HydraException as exc:  # OverrideParseException: which argument, and where
        text = getattr(exc, "override", None) or str(exc)
        key, equal, _ = text.lstrip("+~").partition("=")
        why = grammar_reason(exc, text)
        what = f"cannot read {text!r} ({why})" if equal else f"{text!r} is no key=value"
        raise ConfigError(
            key if equal and key else text,
            f"{what}; a value with brackets, braces, commas, spaces or '=' is quoted, e.g. "
            "key='[a, b]' (Hydra's override grammar)",
        ) from None


def _options(group: str, root: Path) -> dict[str, Any]:
    """The options of config group `group` (e.g. "rep", "hydra/launcher"): name -> its config,
    a node of Hydra's ConfigStore (Hydra's and its plugins' options) or the YAML file of `root`
    (a Path; it takes precedence, as in Hydra's search path)."""
    from hydra.core.config_store import ConfigStore

    stored = ConfigStore.instance().repo
    for part in group.split("/"):
        stored = stored.get(part, {}) if isinstance(stored, dict) else {}
    found = {n.removesuffix(".yaml"): c.node for n, c in stored.items() if n.endswith(".yaml")}
    return dict(sorted((found | {f.stem: f for f in root.joinpath(group).glob("*.yaml")}).items()))


def _elsewhere(node: str, key: str, root: Path) -> str:
    """ "; <key> is a setting of <group>=<option>, ..." for the options of the config group at
    `node` (e.g. hydra.launcher) that set `key`; "" if none does."""
    group = node.replace(".", "/")
    configs = {n: OmegaConf.load(c) if isinstance(c, Path) else c
               for n, c in _options(group, root).items()}  # fmt: skip
    has = [n for n, cfg in configs.items() if isinstance(cfg, DictConfig) and key in cfg]
    return f"; {key} is a setting of {group}={', '.join(has)}" if has else ""


def _refuse_deletions(name: str, taken: list[str], parsed: list[Any]) -> None:
    """`ConfigError` for a `~key` Hydra could not delete: a key the config lacks (the nearest
    named) or a `~key=value` whose value it does not hold (one composition without them)."""
    from hydra import compose

    deleting = [o for o in parsed if o.is_delete()]
    kept = [t for t, o in zip(taken, parsed, strict=True) if not o.is_delete()]
    cfg = compose(name, kept, return_hydra_config=True) if deleting else None
    for key, value in ((o.key_or_group, o.value()) for o in deleting):
        node, _, leaf = key.rpartition(".")
        parent = OmegaConf.select(cfg, node) if node else cfg
        if isinstance(parent, DictConfig) and leaf not in parent:
            refuse_unknown(node, [leaf], sorted(map(str, parent)), "; ~ deletes a key it has")
        if value is not None and (held := OmegaConf.select(cfg, key)) != value:
            raise ConfigError(key, f"is {held!r}, not {value!r}: ~{key}={value} deletes it only "
                              f"at that value; ~{key} deletes it whatever it is")  # fmt: skip


def _refuse_misread(name: str, parsed: list[Any], root: Path) -> None:
    """`ConfigError` for an override Hydra would misread: no mapping for a node of keys of
    conf/<name>.yaml (rotlearn-eval's `ood=kitti`, `data=kitti`), null for a config group
    (`logger=null`), a list for one that takes one option (`data=[kitti,mav]`; a list of
    loggers or callbacks is theirs)."""
    from hydra.core.override_parser.types import OverrideType

    primary = OmegaConf.load(path) if (path := root / f"{name}.yaml").is_file() else {}
    for o in parsed:
        key, value = o.key_or_group, o.value()
        if o.type != OverrideType.CHANGE or o.is_sweep_override() or is_hydra_key(key):
            continue
        if isinstance(node := primary.get(key), DictConfig) and not isinstance(value, dict):
            raise ConfigError(key, f"holds keys to set one by one, {key}.<key>=value "
                              f"({', '.join(map(str, node))}), not {o.input_line}")  # fmt: skip
        several = isinstance(value, list) and key not in COLLECTIONS  # logger=[tensorboard,csv]
        if (value is None or several) and (options := list(_options(key, root))):
            what, how = ("null", f"leave {key}= out for the config's own choice") if value is None \
                else ("a list", f"one run each: -m {key}={','.join(map(str, value))}")  # fmt: skip
            raise ConfigError(key, f"takes one of its options ({', '.join(options)}), not {what};"
                              f" {how}")  # fmt: skip


def _refuse_unchosen_group(name: str, taken: list[str], parsed: list[Any], root: Path) -> None:
    """`ConfigError` for `group=option` where conf/<name>.yaml chooses no option of that group
    (Hydra: "No match in the defaults list"; train's `variant=`), naming the configs whose
    defaults list chooses one."""
    from hydra import compose
    from hydra.core.override_parser.types import OverrideType

    for i, o in enumerate(parsed):
        group = o.key_or_group
        if o.type != OverrideType.CHANGE or not _options(group, root):
            continue
        try:
            cfg = compose(name, taken[:i] + taken[i + 1 :], return_hydra_config=True)
        except Exception:  # another override is at fault
            continue
        if group in cfg.hydra.runtime.choices:
            continue
        groups = sorted(path.name for path in root.iterdir() if path.is_dir())
        users = [
            f"{g}={option}"
            for g in groups
            for option, config in _options(g, root).items()
            if _chooses(config, group)
        ]
        how = f"; {' and '.join(users)} chooses one (e.g. {users[0]} {o.input_line})" if users \
            else ""  # fmt: skip
        raise ConfigError(group, f"conf/{name}.yaml chooses no {group}{how}")


def _chooses(config: Any, group: str) -> bool:
    """Whether an option's config (a YAML file, or a ConfigStore node) lists config group
    `group` in its defaults (`- /variant: a_bingham`, `- override /data: ...`)."""
    node = OmegaConf.load(config) if isinstance(config, Path) else config
    entries = node.get("defaults") if isinstance(node, DictConfig) else None
    keys = [str(k) for entry in entries or [] if isinstance(entry, DictConfig) for k in entry]
    return any(key.split()[-1].strip("/") == group for key in keys)


def _compose(
    name: str, overrides: list[str], root: Path, appendable: Sequence[str] | None = None
) -> tuple[DictConfig, list[str]]:
    """Hydra's compose (with its `hydra` node) and the overrides it took: a `+` before each
    `key=value` of `appendable` (default: every override) whose key the config lacks
    (validation then names a misspelt one); one composition more per `+`."""
    from hydra import compose, initialize_config_dir
    from hydra.core.override_parser.types import OverrideType

    register_schemas()
    parsed, taken = _parse(overrides), list(overrides)
    _refuse_misread(name, parsed, root)
    with initialize_config_dir(config_dir=str(root), version_base="1.3"):
        try:
            while True:
                try:
                    return compose(name, taken, return_hydra_config=True), taken
                except ConfigCompositionException as exc:  # "Could not override 'optim.lrr'"
                    key = getattr(exc.__cause__, "full_key", None)
                    absent = [i for i, o in enumerate(parsed) if o.type == OverrideType.CHANGE
                              and not taken[i].startswith("+") and key
                              and (appendable is None or overrides[i] in appendable)
                              and (o.key_or_group + ".").startswith(f"{key}.")]  # fmt: skip
                    if isinstance(exc, MissingConfigException) or not absent:
                        _refuse_deletions(name, taken, parsed)
                        _refuse_unchosen_group(name, taken, parsed, root)
                        parent = getattr(exc.__cause__, "parent_node", None)
                        node, _, leaf = str(key).rpartition(".")  # Hydra's advice: append it
                        if isinstance(parent, DictConfig) and leaf not in parent:  # data={a: 1}
                            found = arguments(str(parent.get("_target_")), node.split(".")[0])
                            allowed = [p.name for p in found or ()] or sorted(map(str, parent))
                            refuse_unknown(node, [leaf], allowed, _elsewhere(node, leaf, root))
                        raise
                    taken[absent[0]] = f"+{taken[absent[0]]}"
        except MissingConfigException as exc:
            group, _, option = str(exc.missing_cfg_file).rpartition("/")
            if (group, option) not in {(o.key_or_group, str(o.value())) for o in parsed}:
                raise
            real = list(_options(group, root))
            near = difflib.get_close_matches(option, real, n=1, cutoff=0.5)
            hint = f"; did you mean {group}={near[0]}?" if near else ""
            message = f"no option {option!r}{hint}; options: {', '.join(real)}"
            raise ConfigError(group, message) from None


def _composed(
    overrides, output_dir, config_name, root, appendable=None
) -> tuple[DictConfig, list[str]]:
    """`_compose` (Hydra's own keys set too, never given a `+`) with `paths.output_dir` placed:
    `output_dir`, else the run directory Hydra would make."""
    appendable = [o for o in (overrides if appendable is None else appendable)
                  if not is_hydra_key(o)]  # fmt: skip
    cfg, taken = _compose(config_name, list(overrides), Path(root or config_dir()), appendable)
    if output_dir is not None or OmegaConf.is_interpolation(cfg.paths, "output_dir"):
        run_dir = OmegaConf.select(cfg, "hydra.run.dir")
        cfg.paths.output_dir = str(output_dir if output_dir is not None else run_dir)
    return cfg, taken


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
        overrides: e.g. ["rep=a", "optim.lr=1e-3"] (Hydra's own `hydra.*` keys count only
            for where a run would write: the config returned has no `hydra` node).
        output_dir: `paths.output_dir`, where a run of it would write (default: the directory
            `rotlearn-train` would make, hydra.run.dir: outputs/runs/<time>; nothing is written
            here).
        config_name: the primary config; root: the config directory (default: rotlearn's conf/).
        check: validate it (`validate`); False returns it as composed.

    Raises:
        ConfigError: an unknown option or key, or a value its component refuses (naming it).
    """
    cfg, _ = _composed(list(overrides), output_dir, config_name, root)
    with open_dict(cfg):
        del cfg["hydra"]
    if check:
        validate(cfg)
    return cfg


def command_line(
    args: Sequence[str],
    output_dir: str = "new-run",
    config_name: str = "train",
    before_values: Callable[[DictConfig, list[str]], None] | None = None,
    after_values: Callable[[list[dict[str, Any]]], None] | None = None,
) -> tuple[DictConfig, list[str]]:
    """Compose and validate the config of a command line before Hydra starts; returns the
    composed config (with its `hydra` node) and the arguments for Hydra, with `+` before each
    component argument that its YAML does not list. A sweep (-m) is checked with the first value
    of each swept key and with each other value (`sweep_values`). `before_values(cfg, args)`
    runs between the checks from files alone and the values' (which import the components:
    seconds); rotlearn-train refuses an existing output folder there. `after_values(jobs)` gets
    the values of every job checked (plain data), valid: rotlearn-train asks the machine for
    their accelerators. (Composing alone: `command_line_config`.)

    Raises:
        ConfigError: naming the option or key at fault; Hydra's and OmegaConf's own errors where
            the command line does not compose (left for Hydra to report).
    """
    cfg, hydra_args = command_line_config(args, output_dir, config_name)
    jobs = [plain(cfg), *sweep_values(args, output_dir, config_name)]
    for values in jobs:  # from files alone first (fast), as `validate`
        check_keys(values)
    if before_values is not None:
        before_values(cfg, hydra_args)
    check_values(*jobs)
    if after_values is not None:
        after_values(jobs)
    return cfg, hydra_args


def _sweep_jobs(args: Sequence[str]) -> list[list[str]]:
    """The overrides of the jobs checked for a command line's sweep, each swept key at its first
    value in the first: every job of the sweep where it has at most `CHECKED_JOBS`, else, for
    each swept key, each of its other values (of a range: its last) with the other keys at their
    first. One list where nothing is swept.

    Raises:
        ConfigError: a sweep of Hydra's own settings (`hydra.*`: they take one value).
    """
    from hydra.core.override_parser.types import RangeSweep

    options, ranges = [], set()
    for override in _parse([a for a in args if not a.startswith("-")]):
        if not override.is_sweep_override():
            options.append([override.input_line])
        elif is_hydra_key(key := override.key_or_group):
            value, swept = override.input_line.partition("=")[2], key.split("sweeper.params.")[-1]
            how = f"to sweep {swept}: {swept}='{value}'; " if swept != key else ""
            raise ConfigError(key, f"Hydra's own settings take one value, not a sweep; {how}a "
                              f"value for {key} is quoted for Hydra inside the shell's quotes: "
                              f"\"{key}='{value}'\"")  # fmt: skip
        elif values := list(override.sweep_string_iterator()):
            ranges |= {len(options)} if isinstance(override.value(), RangeSweep) else set()
            options.append([f"{override.get_key_element()}={v}" for v in values])
    if math.prod(map(len, options)) <= CHECKED_JOBS:
        return [list(job) for job in itertools.product(*options)]
    first = [lines[0] for lines in options]
    others = [(i, line) for i, lines in enumerate(options)
              for line in (lines[-1:] if i in ranges else lines[1:])]  # fmt: skip
    return [first, *([*first[:i], line, *first[i + 1 :]] for i, line in others)]


def sweep_values(
    args: Sequence[str], output_dir: str = "new-run", config_name: str = "train"
) -> list[dict[str, Any]]:
    """For a sweep (-m), the config (plain data, `checks.plain`) of each other job checked
    (`_sweep_jobs`: every job of a sweep of at most `CHECKED_JOBS`, else each other value of
    each swept key; `command_line_config` composes the first), composed but not validated: an
    unknown option (`rep=a,sixx`) is refused here, and a value or a pair of values that
    `validate` refuses (`rep=a,sixd loss=chordal,bingham`) before the sweep starts, not when
    its job fails. About 0.25 s a job.

    Raises:
        ConfigError: naming the option or key at fault.
    """
    return [plain(_composed(o, output_dir, config_name, None)[0]) for o in _sweep_jobs(args)[1:]]


def command_line_config(
    args: Sequence[str],
    output_dir: str = "new-run",
    config_name: str = "train",
    appendable: Sequence[str] | None = None,
) -> tuple[DictConfig, list[str]]:
    """`command_line` without the validation: the composed config with its `hydra` node (the
    first value of each swept key), and the arguments for Hydra, from one composition (Hydra's
    own keys never get a `+`; a sweep of them is refused). `appendable`: only these
    arguments may get a `+` (a resume's saved overrides never get one, so a file's unknown keys
    cost one composition, not one each)."""
    first = _sweep_jobs(args)[0]  # one override per argument but the flags, in their order
    cfg, taken = _composed(first, output_dir, config_name, None, appendable)
    plus = iter(t != f for t, f in zip(taken, first, strict=True))  # where `_compose` put a +
    return cfg, [a if a.startswith("-") else f"+{a}" if next(plus) else a for a in args]


def validate(cfg: DictConfig) -> None:
    """Check every key and value of a composed train config (`rotlearn.config.checks`): what
    files alone tell (unknown keys, required arguments, data folders), then each value against
    its constructor's annotation and the rules that span keys. Builds only the head and the loss.

    Raises:
        ConfigError: naming the full key, and what was expected or the allowed keys.
    """
    values = plain(cfg)
    check_keys(values)
    check_values(values)


def build(cfg: DictConfig) -> tuple[pl.LightningModule, pl.LightningDataModule]:
    """The model and datamodule of a composed train config: validated, seeded with `cfg.seed`,
    `instantiate(cfg.data)` and `instantiate(cfg.model)` (the regressor with its net, head, loss
    and optimizer from their groups, or the auto-encoder). The model keeps the resolved config
    (`run_config`) for its checkpoints.

    Raises:
        ConfigError: see `validate`; a constructor's own (its key under the node's).
    """
    import lightning.pytorch as pl
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    validate(cfg)
    pl.seed_everything(cfg.seed, workers=True, verbose=False)
    built = []
    for key in ("data", "model"):
        try:
            built.append(instantiate(cfg[key]))
        except InstantiationException as exc:  # for the model: the group a `${net}` names
            if not isinstance(cause := exc.__cause__, ConfigError):
                raise
            part, _, rest = cause.key.partition(".")
            raw = str(OmegaConf.to_container(cfg[key]).get(part, ""))
            node = raw[2:-1] if raw.startswith("${") else f"{key}.{part}"
            raise ConfigError(f"{node}.{rest}" if rest else node, cause.message) from None
    datamodule, model = built
    model.run_config = plain(cfg)
    return model, datamodule
