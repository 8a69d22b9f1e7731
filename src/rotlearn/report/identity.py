"""What tells runs apart: their command-line overrides, the config keys that differ between them,
and the short names and hyper-parameter records made from those (plain Python, no I/O).

A run is described by the settings a person chose: the overrides of its command line (`rep=a`,
`optim.lr=1e-3`) and, in a sweep, the keys swept. Never by plumbing: where files go (`hydra.*`,
`paths.*`), the loggers' and callbacks' own settings (`logger.*`, `callbacks.*`), a resume's
`ckpt_path`, the report layout, the terminal's progress bar and model summary. Used by
`rotlearn-train` (the TensorBoard run's name and its HPARAMS record) and by `rotlearn-report`
(the label of each group of runs).
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

__all__ = [
    "HEADLINE_KEYS",
    "MAX_NAME_LENGTH",
    "hparams_record",
    "is_hydra_key",
    "is_plumbing",
    "override_keys",
    "parse_override",
    "run_name",
    "select",
    "set_keys",
    "short_value",
    "shortened",
    "swept_keys",
]

# Where files go and how they are written, and what the terminal shows: never a setting that
# describes a run (a key, or the node of keys below it).
PLUMBING = ("hydra", "paths", "logger", "callbacks", "ckpt_path", "report",
            "trainer.enable_progress_bar", "trainer.enable_model_summary")  # fmt: skip
# Shown in every run's HPARAMS record, set or not: what it trained (groups by their option).
HEADLINE_KEYS = ("rep", "loss", "net", "data", "optim.lr", "seed")
MAX_NAME_LENGTH = 120  # characters of a run's name (a directory name); longer ones end in a hash
_ABSENT = object()
_TYPED_LIST = re.compile(r"\[[^\[\]]*\]")  # a flat list as a command line types it: [a,b]


def parse_override(text: str) -> tuple[str, str] | None:
    """(key, value as typed) of a Hydra override `key=value`, `+key=value`, `++key=value` or
    `hydra/launcher=joblib`; None for a deletion (`~key`) or anything else."""
    if text.startswith("~"):
        return None
    key, sep, value = text.lstrip("+").partition("=")
    return (key, value) if sep and key else None


def set_keys(overrides: Iterable[str]) -> list[str]:
    """The dotted keys a command line sets, in its order (`a/b=x`, a config group, as `a.b`);
    deletions and flags left out."""
    return [
        key.replace("/", ".") for key, _ in filter(None, map(parse_override, map(str, overrides)))
    ]


def is_hydra_key(key: str) -> bool:
    """Whether a key, or an override, sets Hydra's own config (`hydra.*`, `hydra/<group>`)."""
    key = key.lstrip("+~")
    return key == "hydra" or key.startswith(("hydra.", "hydra/"))


def is_plumbing(key: str) -> bool:
    """True for keys that say where or how files are written or what the terminal shows, not
    what the run is (`PLUMBING`: a key or a node; `a/b`, a config group, is `a.b`)."""
    key = key.replace("/", ".")
    return any(key == p or key.startswith(f"{p}.") for p in PLUMBING)


def override_keys(overrides: Iterable[str]) -> list[str]:
    """The keys a command line sets, in its order, plumbing left out."""
    keys = []
    for text in overrides:
        parsed = parse_override(str(text))
        if parsed is not None and not is_plumbing(parsed[0]) and parsed[0] not in keys:
            keys.append(parsed[0])
    return keys


def select(config: Mapping[str, Any], key: str, default: Any = None) -> Any:
    """The value at the dotted `key` of a nested mapping (`default` where absent)."""
    node: Any = config
    for part in key.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return default
        node = node[part]
    return node


def _value(
    key: str, config: Mapping[str, Any], choices: Mapping[str, str], overrides: Mapping[str, str]
) -> Any:
    """A key's value: a config group's chosen option (`rep` -> "a"), else the resolved config's
    value, else the value as typed on the command line."""
    if key in choices:
        return choices[key]
    found = select(config, key, default=_ABSENT)
    if found is not _ABSENT and not isinstance(found, Mapping):
        return found
    if key in overrides:
        return overrides[key]
    return None


def short_value(value: Any) -> str:
    """A value as a person reads it in a name or a label: numbers in their shortest form
    (1e-3 -> 0.001), booleans and None as true / false / null, a path by its last part, a list
    item by item (also as typed on a command line: `[runs/a/0,runs/a/1]` -> `[0,1]`)."""
    if isinstance(value, bool) or value is None:
        return {True: "true", False: "false", None: "null"}[value]
    if isinstance(value, float):
        return f"{value:g}" if math.isfinite(value) else str(value)
    text = str(value)
    if isinstance(value, str) and _TYPED_LIST.fullmatch(text):
        value = text[1:-1].split(",")
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(short_value(v) for v in value) + "]"
    if "/" in text.strip("/"):
        text = text.rstrip("/").rsplit("/", 1)[-1]
    return text.replace("/", "_")


def _hparam(value: Any) -> bool | int | float | str:
    """A value TensorBoard's HPARAMS view shows as it is: numbers as numbers, booleans as true /
    false (not 1.0 / 0.0), everything else as text."""
    if isinstance(value, bool):
        return value
    if isinstance(value, (int, float)):
        return value
    return short_value(value) if isinstance(value, (list, tuple)) or value is None else str(value)


def hparams_record(
    config: Mapping[str, Any], overrides: Sequence[str], choices: Mapping[str, str] | None = None
) -> dict[str, Any]:
    """A run's record for TensorBoard's HPARAMS view: `HEADLINE_KEYS` (rep, loss, net, data,
    optim.lr, seed), then every key its command line set (plumbing left out), each with its
    value: a config group's option (`data` -> "tiny"), else the resolved config's value.

    Args:
        config: the run's resolved config (plain containers).
        overrides: its command-line overrides (Hydra's `hydra.overrides.task`).
        choices: config group -> chosen option (Hydra's `hydra.runtime.choices`); for a config
            composed without Hydra's runtime, the head's name stands for `rep` and the class
            named by each group's `_target_` for the others.
    """
    choices = dict(choices or {})
    if "rep" not in choices and select(config, "rep.name") is not None:
        choices["rep"] = str(select(config, "rep.name"))
    for group in ("loss", "net", "data"):
        target = select(config, f"{group}._target_")
        if group not in choices and isinstance(target, str):
            choices[group] = target.rsplit(".", 1)[-1]
    typed = dict(p for p in (parse_override(str(o)) for o in overrides) if p is not None)
    record = {}
    for key in [*HEADLINE_KEYS, *override_keys(overrides)]:
        if key not in record:
            record[key] = _hparam(_value(key, config, choices, typed))
    return record


def swept_keys(jobs: Sequence[Sequence[str]]) -> list[str]:
    """The keys whose value differs between the jobs of a sweep (each job: its overrides), in
    the order they first appear; plumbing left out."""
    values: dict[str, set[str]] = {}
    for job in jobs:
        parsed = dict(p for p in (parse_override(str(o)) for o in job) if p is not None)
        for key in {*values, *parsed}:
            values.setdefault(key, set()).add(parsed.get(key, "<unset>"))
    order = override_keys(o for job in jobs for o in job)
    return [key for key in order if len(values.get(key, ())) > 1]


def run_name(
    config: Mapping[str, Any],
    overrides: Sequence[str],
    choices: Mapping[str, str] | None = None,
    keys: Sequence[str] | None = None,
) -> str:
    """A run's name as `key=value,key=value`: the keys that tell it apart (`keys`: in a sweep,
    the swept ones; None: every key its command line sets), each value as `short_value` writes
    it (`rep=a,optim.lr=0.001`). "defaults" for a run that sets nothing. A plain file name: no
    "/", at most `MAX_NAME_LENGTH` characters (a longer one is cut and ends in a hash of it)."""
    typed = dict(p for p in (parse_override(str(o)) for o in overrides) if p is not None)
    wanted = list(keys) if keys else override_keys(overrides)
    choices = dict(choices or {})
    parts = [f"{k}={short_value(_value(k, config, choices, typed))}" for k in wanted]
    name = ",".join(parts).replace("/", "_") or "defaults"
    if name in (".", ".."):
        name = "defaults"
    return shortened(name, MAX_NAME_LENGTH)


def shortened(text: str, limit: int) -> str:
    """`text` cut to `limit` characters where it is longer, ending in `~` and a hash of the
    whole (two long texts that differ only past the cut stay apart)."""
    if len(text) <= limit:
        return text
    digest = hashlib.sha1(text.encode()).hexdigest()[:8]
    return f"{text[: limit - 9]}~{digest}"
