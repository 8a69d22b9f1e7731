"""Replaying a run directory's saved overrides on resume, through the same allowlist as checkpoints.

`rotlearn-train ckpt_path=<run>` continues a run with the overrides it was started with, read
from `<run>/.hydra/overrides.yaml`. That file is data someone may have sent: an override such as
`net._target_=torch.load`, `+net.f._target_=builtins.open` or `hydra.callbacks.x._target_=...`
would run code when Hydra composes and instantiates the run. `saved_overrides` reads the file as
plain YAML, bounded (a regular file inside the run, at most 256 KiB, no aliases: `rotlearn.io`),
at most `MAX_OVERRIDES` strings, and refuses Hydra's own keys, sweeps, and config group choices
that are not an option's name (a path to a YAML file, `group@package=`): a run's saved overrides
hold none of these. `replayed_config` composes the config that will run from them and the user's new
overrides, exactly as Hydra will, and checks it whole with `rotlearn.trust.trusted_config` BEFORE
Hydra starts: nothing is written and nothing is built from a refused file. `quoted` makes a path
(the run directory, the checkpoint) a safe override value whatever characters it holds.
"""

from __future__ import annotations

import re
import shlex
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from rotlearn.io import UnreadableFileError, read_yaml
from rotlearn.paths import config_dir
from rotlearn.report.identity import is_hydra_key
from rotlearn.trust import UntrustedConfigError, trusted_config

__all__ = ["quoted", "replayed_config", "saved_overrides"]

MAX_OVERRIDES = 1000  # one run's command line; a file with more is not a run's
MAX_OVERRIDE_CHARS = 8192  # one override's text
# The resolvers a saved override may name: those that read the config alone (and rotlearn's own,
# `rl.*`). `${oc.env:...}` would read the environment of whoever resumes a received run into
# its config, its folders and files; `oc.decode` and `oc.create` read a string as config again,
# so an escaped `\${oc.env:...}` in their argument would do the same.
CONFIG_RESOLVERS = ("hydra", "now", "oc.select", "oc.deprecated", "oc.dict.keys",
                    "oc.dict.values")  # fmt: skip
# A config group option's name: Hydra finds `<group>/<name>.yaml` only where the group is (no
# path separator; no leading dot); a name that is no option is refused with the nearest ones.
_OPTION_NAME = re.compile(r"\w[\w.-]*")


def quoted(value: str) -> str:
    """`value` as a quoted Hydra override value that Hydra and OmegaConf read back as exactly
    `value`, whatever characters it holds (any a file name may have: spaces, quotes, `=`, `,`,
    non-ASCII letters, backslashes, `${`): `key=` + quoted(path) is a safe override.

    OmegaConf reads `\\${` as a literal `${` (and doubles backslashes before one); Hydra's
    quoted strings then escape each quote and the backslashes before a quote or the end.
    """
    text = re.sub(r"(\\*)\$\{", lambda m: m.group(1) * 2 + "\\${", value)
    text = re.sub(r"(\\*)(?='|$)", lambda m: m.group(1) * 2, text)
    return "'" + text.replace("'", "\\'") + "'"


def shell_word(key: str, value: str) -> str:
    """`key=value` as one shell word of a printed command that a user pastes, Hydra reading
    back `value` (quoted for Hydra and the shell where it must be)."""
    if re.fullmatch(r"[\w./@+-]+", value):
        return f"{key}={value}"
    return shlex.quote(f"{key}={quoted(value)}")


def resume_word(run: str | Path) -> str:
    """`ckpt_path=<run>` as one shell word of a printed resume command: rotlearn reads the value
    as written, not through Hydra's grammar, so it is quoted for the shell alone."""
    return shlex.quote(f"ckpt_path={run}")


def _parse(overrides: list[str], source: Path) -> None:
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except HydraException as exc:  # OverrideParseException: which override, and where
        from rotlearn.config import grammar_reason

        text = getattr(exc, "override", None) or ""
        raise UntrustedConfigError(
            f"{source}: override {text!r} is not Hydra's override grammar "
            f"({grammar_reason(exc, text)})"
        ) from None
    for override in parsed:
        key = override.key_or_group
        if is_hydra_key(key):
            raise UntrustedConfigError(
                f"{source}: override {override.input_line!r} sets Hydra's own config key {key}; "
                "a run's saved overrides never do"
            )
        if override.is_sweep_override():
            raise UntrustedConfigError(
                f"{source}: override {override.input_line!r} is a sweep, not one run's value"
            )
        for name in _resolvers(override.value(), override.input_line, source):
            if name not in CONFIG_RESOLVERS and not name.startswith("rl."):
                raise UntrustedConfigError(
                    f"{source}: override {override.input_line!r} reads ${{{name}:...}}: a saved "
                    "override may use only the resolvers that read the config (a received run "
                    "could read your environment this way); set that value on the command line"
                )
    _refuse_configs_from_elsewhere(parsed, source)


def _refuse_configs_from_elsewhere(parsed: list[Any], source: Path) -> None:
    """A saved override may choose a config group's option only by a name, and only where the
    group puts it. Hydra reads `group=<path>` as a YAML file at that path relative to the
    group's folder (`data=../../<received run>/notes` makes a file of the run the data config,
    and its `# @package _global_` may set Hydra's own callbacks, which Hydra builds), and
    `group@<package>=option` places a config under another node (`hydra.callbacks`): neither
    is an option of rotlearn's, and neither is in a run's saved overrides. A key is a group as
    Hydra's config repository sees it (conf/, rotlearn's schemas, plugins' search paths)."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        loader = GlobalHydra.instance().config_loader()
        for override in parsed:
            group = override.key_or_group
            if "/" not in group and not loader.repository.group_exists(group):
                continue  # a value key (`seed=3`): Hydra reads its value as a value
            value = override.value()
            chosen = value if isinstance(value, list) else [value]
            paths = [v for v in chosen if v is not None and not _OPTION_NAME.fullmatch(str(v))]
            if override.package is None and not paths:
                continue  # a name: an option, or refused later with the nearest options
            options = ", ".join(loader.get_group_options(group)) or "none"
            raise UntrustedConfigError(
                f"{source}: override {override.input_line!r} "
                + (f"puts config group {group} under {override.package}"
                   if override.package is not None else
                   f"chooses {paths[0]!r} for config group {group}, not an option's name "
                   f"(options: {options})")
                + "; a run's saved overrides choose rotlearn's own configs by name"
            )  # fmt: skip


def _resolvers(value: Any, line: str, source: Path) -> Iterator[str]:
    """The names of the resolvers OmegaConf would call to resolve `value` (a parsed override's
    value: a string, or lists and dicts of them), read with OmegaConf's own grammar; a name
    built from an interpolation (`${oc.${x}:...}`) as written, `${` and all."""
    from omegaconf.errors import GrammarParseError
    from omegaconf.grammar.gen.OmegaConfGrammarParser import OmegaConfGrammarParser
    from omegaconf.grammar_parser import parse

    if isinstance(value, dict | list):
        for item in value.values() if isinstance(value, dict) else value:
            yield from _resolvers(item, line, source)
        return
    if not isinstance(value, str) or "${" not in value:
        return
    try:
        nodes = [parse(value)]
    except GrammarParseError:
        raise UntrustedConfigError(
            f"{source}: override {line!r} holds {value!r}, which OmegaConf cannot read"
        ) from None
    while nodes:
        node = nodes.pop()
        if isinstance(node, OmegaConfGrammarParser.ResolverNameContext):
            yield node.getText()
        nodes.extend(getattr(node, "children", None) or ())


def saved_overrides(run_dir: str | Path) -> list[str]:
    """The overrides a run was started with, read as untrusted data (not yet composed: see
    `replayed_config`).

    Args:
        run_dir: the run directory (holding `.hydra/overrides.yaml`).

    Returns:
        The saved overrides, in order, as strings.

    Raises:
        FileNotFoundError: the run has no `.hydra/overrides.yaml`.
        UntrustedConfigError: naming the file and the override at fault: not a regular file
            inside the run, too large, not YAML (or with aliases), not a list of at most
            `MAX_OVERRIDES` strings, a Hydra key or a sweep.
    """
    source = Path(run_dir) / ".hydra" / "overrides.yaml"
    try:
        overrides = read_yaml(source, "overrides file", root=run_dir) or []
    except FileNotFoundError:
        raise FileNotFoundError(f"{run_dir} is not a rotlearn run (no {source})") from None
    except UnreadableFileError as exc:
        raise UntrustedConfigError(str(exc)) from None
    if not isinstance(overrides, list) or not all(isinstance(o, str) for o in overrides):
        raise UntrustedConfigError(f"{source}: expected a list of override strings")
    if len(overrides) > MAX_OVERRIDES or any(len(o) > MAX_OVERRIDE_CHARS for o in overrides):
        raise UntrustedConfigError(
            f"{source}: more than {MAX_OVERRIDES} overrides, or one longer than "
            f"{MAX_OVERRIDE_CHARS} characters: not one run's command line"
        )
    _parse(overrides, source)
    return overrides


def replayed_config(args: list[str], run_dir: str | Path, config_name: str = "train"):
    """The config Hydra will run for the command line `args` (the run's saved overrides, then
    the user's) in `run_dir`, composed exactly as Hydra composes it (Hydra's own keys aside;
    `paths.output_dir` resolved to the run directory, as Hydra resolves it, unless an override
    sets it), and checked with `rotlearn.trust.trusted_config` before anything is built from it.

    Raises:
        UntrustedConfigError: naming the run's overrides file and the key path at fault: the
            overrides do not compose, or the composed config names a `_target_` off the allowlist
            or holds an interpolation an override brought in.
    """
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    import rotlearn.config.resolvers  # noqa: F401  (the configs' own resolvers)
    from rotlearn.cli.rundir import place_output_dir

    source = Path(run_dir) / ".hydra" / "overrides.yaml"
    overrides = [a for a in args if not is_hydra_key(a)]
    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            cfg = compose(config_name=config_name, overrides=overrides)
    except (HydraException, OmegaConfBaseException) as exc:
        said = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise UntrustedConfigError(f"{source}: the overrides do not compose: {said}") from None
    place_output_dir(cfg, run_dir)
    trusted_config(cfg, source)  # resolved and walked; nothing is built from a refused config
    return cfg
