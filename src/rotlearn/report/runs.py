"""Collect runs from their directories alone, and group them into settings.

Each run's `.hydra/config.yaml` is read as plain YAML data: never resolved (a run directory is
untrusted; an interpolation such as `${oc.env:...}` stays text); a job folder that leads out of
its sweep (a symlink to a run elsewhere) is not read. The report layout, a run's `report` node,
is checked once (`rotlearn.report.layout.layout_of`): a value of the wrong kind is refused naming
the file and key, and each plot is drawn into the report's folder under a plain `.png` name.

Runs are grouped by every config key whose value differs between them, except the trial keys:
those the sweep or experiment declares (`report.trial_keys`; `sweep=lr` declares its trials,
their seeds and the lr drawn for each) and the seeds. `group_by` replaces that rule (exactly
those keys), `pool` adds trial keys; a key may name a config group (`rep`: every key below it)
or one key (`optim.lr`).

A setting is labelled by the value of `report.lead` (the head's name), then each other grouping
key as `group=option` where the config group's option differs between the runs (`loss=bingham`),
else as `key=value` (`optim.lr=0.001`; a key left null is not shown: `quat` beside `sixd
callbacks.ood.autoencoder_ckpt=kitti_ae`, not `quat callbacks.ood.autoencoder_ckpt=null`).
"""

from __future__ import annotations

import difflib
import logging
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from rotlearn import io
from rotlearn.io import read_json
from rotlearn.paths import EVALUATED_FILE, TESTED_WEIGHTS
from rotlearn.report.identity import parse_override, short_value
from rotlearn.report.layout import layout_of

__all__ = [
    "NOT_READ",
    "NOT_SETTINGS",
    "RUN_MARKS",
    "collect_runs",
    "is_run",
    "label_without",
    "matches",
    "run_dirs",
]

log = logging.getLogger("rotlearn")
NOT_SETTINGS = ("hydra", "paths", "report")  # per-run paths, and the report layout itself
MODEL_PARTS = ("rep", "loss", "scheduler")  # settings only where the model takes them (`${rep}`)
_MISSING = "-"
NOT_READ = "NOT READ"  # the status of a job whose folder leads out of its sweep
RUN_MARKS = (".hydra/config.yaml", "status.json", "metrics.json")  # what makes a run directory
MAX_ERROR = 2000  # characters of a run's error shown (a received status.json held 10 MB of it)


def read_yaml(path: Path, kind: str = "YAML config", run: Path | None = None) -> Any:
    """Plain data of a run's YAML file (never resolved, no tags, no aliases, nesting and size
    capped, a regular file inside the run: `rotlearn.io.read_yaml`; `run`: the run directory,
    default the file's grandparent, as for `.hydra/*.yaml`); None if missing or refused (a
    warning names the file and why)."""
    try:
        return io.read_yaml(path, kind, root=run or path.parent.parent)
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        log.warning("%s (ignored)", exc)
        return None


def _record(run: Path, name: str) -> dict[str, Any]:
    """A JSON record of a run as a dict (read bounded: `rotlearn.io.read_json`): {} where it is
    missing, refused or not a JSON object (a warning names the file)."""
    data = read_json(run / name, root=run)
    if data is not None and not isinstance(data, dict):
        log.warning("%s: not a JSON object (a %s); ignored", run / name, type(data).__name__)
    return data if isinstance(data, dict) else {}


def flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    """{"a.b": leaf} of nested mappings; lists and other leaves are kept whole."""
    if not isinstance(tree, Mapping):
        return {prefix: tree} if prefix else {}
    flat = {}
    for key, value in tree.items():
        flat.update(flatten(value, f"{prefix}.{key}" if prefix else str(key)))
    return flat


def cell(value: Any) -> Any:
    """A config value as one summary cell: numbers and text as they are, others as YAML."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return yaml.safe_dump(value, default_flow_style=True).strip()


def is_run(folder: Path) -> bool:
    """Whether `folder` is a run (or evaluation) directory: it holds a file one writes
    (`RUN_MARKS`), its config or only its records (a config lost or deleted)."""
    return any((folder / mark).is_file() for mark in RUN_MARKS)


def run_dirs(root: Path) -> list[Path]:
    """The run directories of a sweep directory (by job number), or `root` if it is a run. A
    job folder that leads out of the sweep (a symlink to a folder elsewhere) is not read: a
    warning names it."""
    if is_run(root):
        return [root]
    folders = root.iterdir() if root.is_dir() else ()
    jobs = []
    for folder in folders:
        if folder.name.startswith(".") or not folder.is_dir():
            continue
        try:
            io.resolve_inside(root, folder, "job folder")
        except ValueError as exc:
            log.warning("%s; not read (a job folder must lie inside its sweep)", exc)
            continue
        if is_run(folder):
            jobs.append(folder)
    return sorted(
        jobs, key=lambda p: (not p.name.isdigit(), int(p.name) if p.name.isdigit() else 0, p.name)
    )


def run_choices(run: Path, overrides: list[str], hydra: Any = None) -> dict[str, str]:
    """{config group: chosen option} of a run: `.hydra/hydra.yaml`'s runtime choices (or those
    of `hydra`, an evaluation's record of the run it evaluated), then the group overrides
    (`loss=bingham`) of its command line."""
    hydra = hydra if hydra is not None else read_yaml(run / ".hydra" / "hydra.yaml")
    runtime = (hydra or {}).get("hydra", {}).get("runtime", {}) if isinstance(hydra, dict) else {}
    choices = runtime.get("choices") if isinstance(runtime, dict) else None
    choices = {str(k): str(v) for k, v in choices.items()} if isinstance(choices, dict) else {}
    for text in overrides:
        parsed = parse_override(text)
        if parsed is not None and "." not in parsed[0]:
            choices[parsed[0]] = parsed[1]
    return choices


def _unused(cfg: Mapping[str, Any]) -> set[str]:
    """The top-level nodes that are no setting of a run: `NOT_SETTINGS`, and each of
    `MODEL_PARTS` that its `model` node does not take (the auto-encoder has no head or loss)."""
    model = cfg.get("model")
    if not isinstance(model, Mapping):
        return set(NOT_SETTINGS)
    taken = {str(v)[2:-1] for v in model.values() if str(v).startswith("${")}
    return {*NOT_SETTINGS, *(p for p in MODEL_PARTS if p not in taken)}


def _roots(root: str | Path | Sequence[str | Path]) -> list[Path]:
    return [Path(r) for r in root] if isinstance(root, (list, tuple)) else [Path(root)]


def matches(key: str, specs: Sequence[str]) -> bool:
    """`key` is one of `specs`, or lies below one (`rep` matches `rep.name`)."""
    return any(key == spec or key.startswith(f"{spec}.") for spec in specs)


def _weights(said: Any) -> str | None:
    """metrics.json's `tested_weights` where it is one of `TESTED_WEIGHTS` (a received file's
    other text is not shown)."""
    return said if isinstance(said, str) and said in TESTED_WEIGHTS else None


def collect_runs(
    root: str | Path | Sequence[str | Path],
    group_by: Sequence[str] | None = None,
    pool: Sequence[str] = (),
) -> pd.DataFrame:
    """One row per run directory below `root` (one sweep or run directory, or a list of them,
    pooled) and per job in a `jobs.json` without one: job (`<sweep name>/<job>` when several
    roots), dir, status, error, overrides, `setting` (the label of its group; module docstring),
    the lead, grouping and trial config keys (dotted paths, values as written), `group:<name>`
    (each config group's choice), `tested_weights` (last or best), then the run's numeric
    final metrics. `attrs["layout"]` is the report layout, `attrs["grouping"]` the grouping
    keys.

    Args:
        root: a sweep or run directory, or several (pooled into one table).
        group_by: group by exactly these keys (config groups or keys); None: every key that
            differs between the runs, but the trial keys.
        pool: more trial keys (pooled within a group).
    """
    roots = _roots(root)
    runs, seen = [], set()
    for sweep in roots:
        for run in run_dirs(sweep):
            if (where := run.resolve()) not in seen:  # a run given twice: reported once
                seen.add(where)
                runs.append((sweep, run))
    rows, configs, sources, flats, choices = [], [], [], [], []
    for sweep, run in runs:
        evaluated = read_yaml(run / EVALUATED_FILE, run=run)  # an evaluation: the run it evaluated
        cfg = evaluated if isinstance(evaluated, dict) else read_yaml(run / ".hydra/config.yaml")
        evaluation = isinstance(evaluated, dict)
        sources.append(run / EVALUATED_FILE if evaluation else run / ".hydra" / "config.yaml")
        if not isinstance(cfg, dict) or not cfg:  # missing, empty, refused or not a mapping
            log.warning("%s: missing, empty, refused or not a mapping; the run is reported as "
                        "'(config unreadable)'", run / ".hydra" / "config.yaml")  # fmt: skip
            cfg = {}
        overrides = read_yaml(run / ".hydra" / "overrides.yaml", "overrides file")
        overrides = [str(o) for o in overrides] if isinstance(overrides, list) else []
        metrics, status = _record(run, "metrics.json"), _record(run, "status.json")
        if not isinstance(status.get("status", ""), str):
            log.warning("%s: status is not a string; ignored", run / "status.json")
            status = {}
        state = status.get("status") or ("COMPLETED" if metrics else "INCOMPLETE")
        rows.append(
            {
                "job": _job_name(sweep, run, roots),
                "dir": str(run),
                "status": state,
                "error": _cut(status.get("error"), run / "status.json"),  # INTERRUPTED: resume
                "overrides": " ".join(overrides),
                "tested_weights": _weights(metrics.get("tested_weights")),
                **{
                    k: v
                    for k, v in metrics.items()
                    if isinstance(v, (int, float)) and not isinstance(v, bool)
                },
                "diverged": d if isinstance(d := metrics.get("diverged"), bool) else None,
            }
        )
        configs.append(cfg)
        unused = _unused(cfg)
        flats.append({k: v for k, v in flatten(cfg).items() if k.split(".")[0] not in unused})
        if isinstance(evaluated, dict):  # the evaluated run's choices (its `hydra` node); the
            chosen = run_choices(run, [], evaluated)  # command line's keys are in `cfg`
        else:
            chosen = run_choices(run, overrides)
        choices.append({k: v for k, v in chosen.items() if k not in unused})
    layout = layout_of(configs, sources)
    grouping = _grouping_keys(flats, layout, group_by, pool)
    columns, labels, parts = _settings(flats, choices, layout, grouping, group_by is not None)
    for row, values, label, chosen in zip(rows, columns, labels, choices, strict=True):
        row.update({k: v for k, v in values.items() if k not in row}, setting=label)
        row.update({f"group:{k}": v for k, v in chosen.items() if not k.startswith("hydra/")})
    unstarted = []
    for r in roots:
        seen = {Path(row["dir"]).name for row in rows if Path(row["dir"]).parent == r}
        for job in _unstarted_jobs(r, seen):
            unstarted.append({**job, "job": _job_name(r, r / str(job["job"]), roots)})
    frame = pd.DataFrame(rows + unstarted)
    frame.attrs["layout"] = layout
    frame.attrs["grouping"] = grouping
    frame.attrs["label_parts"] = {row["dir"]: p for row, p in zip(rows, parts, strict=True)}
    return frame


def label_without(frame: pd.DataFrame, keys: Sequence[str]) -> pd.Series:
    """Each run's setting label without the parts made from `keys` (config groups or keys):
    the series of a plot whose x axis is one of them."""
    parts = frame.attrs.get("label_parts", {})

    def label(row: pd.Series) -> str:
        kept = [p for key, p in parts.get(row["dir"], []) if not matches(key, keys)]
        return " ".join(kept) or "all"

    return frame.apply(label, axis=1) if len(frame) else pd.Series(dtype=str)


def _cut(error: Any, source: Path) -> Any:
    """A run's error as the report shows it: text past `MAX_ERROR` characters cut, saying where
    the whole is."""
    if not isinstance(error, str) or len(error) <= MAX_ERROR:
        return error
    return f"{error[:MAX_ERROR]}... ({len(error)} characters; the whole in {source})"


def _job_name(sweep: Path, run: Path, roots: list[Path]) -> str:
    """A run's name in the report: its directory's name, `<sweep>/<run>` when pooling roots."""
    if len(roots) == 1:
        return run.name
    return f"{sweep.name}/{run.name}" if run != sweep else sweep.name


def _grouping_keys(
    flats: list[dict[str, Any]],
    layout: Mapping[str, Any],
    group_by: Sequence[str] | None,
    pool: Sequence[str],
) -> list[str]:
    """The config keys that make the groups (module docstring), sorted.

    Raises:
        ValueError: a `group_by` key that no run has (nor any key below it).
    """
    flats = [flat for flat in flats if flat]  # a run without a readable config sets no key
    keys = sorted({k for flat in flats for k in flat})
    if group_by is not None:
        for spec in (s for s in group_by if flats and not any(matches(k, [s]) for k in keys)):
            near = difflib.get_close_matches(spec, keys, n=1)
            hint = f"; did you mean {near[0]}?" if near else ""
            raise ValueError(f"--group-by {spec}: no run has this config key{hint}")
        return [k for k in keys if matches(k, group_by)]
    trial = [*layout["trial_keys"], *pool]
    differ = [k for k in keys if len({repr(f.get(k, _MISSING)) for f in flats}) > 1]
    return [k for k in differ if not matches(k, trial)]


def _settings(
    flats: list[dict[str, Any]],
    choices: list[dict[str, str]],
    layout: Mapping[str, Any],
    grouping: list[str],
    explicit: bool = False,
) -> tuple[list[dict[str, Any]], list[str], list[list[tuple[str, str]]]]:
    """Per run: its config columns ({key: value} of the lead, grouping and trial keys) and its
    setting label (the lead's value, unless `explicit` grouping leaves its group out, then
    `group=option` or `key=value` of each other grouping key), and the (key, text) parts of
    that label."""
    lead = str(layout.get("lead") or "")
    trial = layout["trial_keys"]
    keys = sorted({k for flat in flats for k in flat})
    shown = [k for k in keys if k == lead or k in grouping or matches(k, trial)]
    lead_node = lead.split(".")[0]
    grouped_nodes = {k.split(".")[0] for k in grouping}
    # a group's option names the setting only where it differs (else two settings that differ in
    # one of its keys would read the same)
    varied = {
        node
        for node in grouped_nodes
        if len({c.get(node) for c in choices}) > 1 and all(node in c for c in choices)
    }
    text = {key: _distinct_text([f[key] for f in flats if f.get(key) is not None])
            for key in grouping}  # fmt: skip
    # null is said where another run lacks the key: both would read as nothing
    said_null = {k for k in grouping if any(f and k not in f for f in flats)
                 and any(k in f and f[k] is None for f in flats)}  # fmt: skip
    columns, labels, all_parts = [], [], []
    for flat, chosen in zip(flats, choices, strict=True):
        columns.append({k: cell(flat.get(k)) for k in shown})
        lead_shown = bool(lead) and lead in flat and (not explicit or lead_node in grouped_nodes)
        parts = [(lead, short_value(flat[lead]))] if lead_shown else []
        for key in grouping:
            node = key.split(".")[0]
            if node == lead_node and lead_shown:
                continue
            if node in varied:
                part = f"{node}={chosen[node]}"
            elif key not in flat or ((value := flat[key]) is None and key not in said_null):
                continue  # unset, or absent: the settings that set it say so
            elif value is None:
                part = f"{key}=null"
            elif key.endswith("._target_"):  # the class by its name: loss=BinghamNLLLoss
                part = f"{key.removesuffix('._target_')}={str(value).rpartition('.')[2]}"
            else:
                part = f"{key}={text[key](value)}"
            if part not in [p for _, p in parts]:
                parts.append((key, part))
        if not flat:  # a damaged or missing .hydra/config.yaml
            parts = [("", "(config unreadable)")]
        labels.append(" ".join(p for _, p in parts) or chosen.get("model") or "all")
        all_parts.append(parts)
    return columns, labels, all_parts


def _distinct_text(values: Sequence[Any]) -> Callable[[Any], str]:
    """How a label writes one key's values: `short_value`, unless that gives two different values
    the same text (data roots that end in the same folder, numbers alike to 6 digits); then
    each by as many of its last `/`-parts as tell them apart, in full at most."""
    distinct = list({repr(v): v for v in values}.values())
    if len({short_value(v) for v in distinct}) == len(distinct):
        return short_value
    for n in range(1, max(len(_path_parts(v)) for v in distinct) + 1):
        if len({"/".join(_path_parts(v)[-n:]) for v in distinct}) == len(distinct):
            return lambda value: "/".join(_path_parts(value)[-n:])
    return str


def _path_parts(value: Any) -> list[str]:
    return str(value).rstrip("/").split("/")


def _unstarted_jobs(root: Path, seen: set[str]) -> list[dict[str, Any]]:
    """Rows for the jobs that `<root>/jobs.json` lists but that have no run directory (yet): those
    that never ran (PENDING), or died before Hydra wrote their config; or whose folder leads out
    of the sweep (`NOT_READ`: `run_dirs` did not read it)."""
    summary = read_json(root / "jobs.json", root=root)
    jobs = summary.get("jobs", []) if isinstance(summary, dict) else []
    rows = []
    for i, job in enumerate(jobs if isinstance(jobs, list) else []):
        if not isinstance(job, dict):
            continue
        name = Path(str(job["dir"])).name if job.get("dir") else str(job.get("num"))
        if name in seen:
            continue
        overrides = job.get("overrides") if isinstance(job.get("overrides"), list) else []
        status, error = job.get("status", "PENDING"), job.get("error") or "never ran"
        if not isinstance(status, str):
            log.warning("%s: jobs[%d].status is not a string; ignored", root / "jobs.json", i)
            status = "PENDING"
        try:  # its folder is there, but `run_dirs` did not read it
            io.resolve_inside(root, root / name, "job folder")
        except ValueError as exc:
            status, error = NOT_READ, f"{exc}: not read"
        rows.append(
            {
                "job": name,
                "dir": str(job["dir"]) if job.get("dir") else None,
                "status": status,
                "error": _cut(error, root / "jobs.json"),
                "overrides": " ".join(str(o) for o in overrides),
            }
        )
    return rows
