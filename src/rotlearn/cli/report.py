"""`rotlearn-report <sweep dir>`: tables and plots of a sweep, made from its run directories alone.

Each run's `.hydra/config.yaml` is read as plain YAML data: never resolved (a run directory is
untrusted; an interpolation such as `${oc.env:...}` stays text). Runs are grouped into settings by
the config keys whose values differ between them, leaving out the keys that vary between trials of
one setting (`report.pooled`: seeds, trials, the lr of an lr sweep) and the x keys of box plots;
a setting is labelled by `report.lead` (the head's name) and its other differing config groups as
`group=choice` (the choice from `.hydra/hydra.yaml` or the overrides) or keys as `key=value`.

The layout comes from the sweep's `report` config node (an experiment's, e.g.
`conf/experiment/synthetic_phi_max.yaml`), over `DEFAULT_REPORT`::

    report:
      lead: rep.name                  # the key whose value starts each row label
      pooled: [trial, seed, data.seed, optim.lr]
      plots:                          # drawn when the sweep has what they need
        - {kind: curves, metrics: [train/err_mean, val/err_mean]}   # paper Fig. 3
        - {kind: box, x: data.phi_max_deg, label: phi_max}           # paper Fig. 4

Writes into the sweep directory (or --out): `summary.csv` (one row per job, failed, interrupted and
never-run ones too, with the differing and pooled config keys), `report.md` (per-setting
percentiles of the final test error over trials; per box plot, the median test error per x value;
OOD Table I rows of runs with an `ood.csv`; the jobs that failed, were interrupted or never ran:
those listed PENDING in the sweep's jobs.json), a `curves` plot (`curves.png`: per-epoch median
over trials with a 10-90 % band per setting, one panel per metric) and a `box` plot
(`<label>_box.png`: box plots of log10 per-sample test error, `test_errors.json`, per x value and
setting).
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from rotlearn.cli.report_plots import draw_plots, setting_order
from rotlearn.io import read_json, write_text_atomic
from rotlearn.ood.report import TABLE_COLUMNS, markdown_table, table_rows

__all__ = ["DEFAULT_REPORT", "collect_runs", "main", "make_report"]

log = logging.getLogger("rotlearn")
DEFAULT_REPORT: dict[str, Any] = {
    "lead": "rep.name",
    "pooled": ["trial", "seed", "data.seed", "optim.lr"],
    "plots": [{"kind": "curves"}],
}
NOT_SETTINGS = ("hydra", "paths", "report")  # per-run paths, and the report layout itself
_MISSING = "-"


def _read_yaml(path: Path) -> Any:
    """Plain data of a YAML file (never resolved, no tags); None if unreadable."""
    try:
        return yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return None


def _flatten(tree: Any, prefix: str = "") -> dict[str, Any]:
    """{"a.b": leaf} of nested mappings; lists and other leaves are kept whole."""
    if not isinstance(tree, Mapping):
        return {prefix: tree} if prefix else {}
    flat = {}
    for key, value in tree.items():
        flat.update(_flatten(value, f"{prefix}.{key}" if prefix else str(key)))
    return flat


def _cell(value: Any) -> Any:
    """A config value as one summary/label cell: numbers and text as they are, others as YAML."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return yaml.safe_dump(value, default_flow_style=True).strip()


def _run_dirs(root: Path) -> list[Path]:
    if (root / ".hydra" / "config.yaml").is_file():
        return [root]
    return sorted(
        (p.parent.parent for p in root.glob("*/.hydra/config.yaml")),
        key=lambda p: (not p.name.isdigit(), int(p.name) if p.name.isdigit() else 0, p.name),
    )


def _choices(run: Path, overrides: list[str]) -> dict[str, str]:
    """{config group: chosen option} of a run: `.hydra/hydra.yaml`'s runtime choices, then the
    group overrides (`loss=bingham`) of its command line."""
    hydra = _read_yaml(run / ".hydra" / "hydra.yaml")
    runtime = (hydra or {}).get("hydra", {}).get("runtime", {}) if isinstance(hydra, dict) else {}
    choices = runtime.get("choices") if isinstance(runtime, dict) else None
    choices = {str(k): str(v) for k, v in choices.items()} if isinstance(choices, dict) else {}
    for text in overrides:
        key, sep, value = text.lstrip("+~").partition("=")
        if sep and "." not in key:
            choices[key] = value
    return choices


def _layout(configs: list[dict[str, Any]]) -> dict[str, Any]:
    """The sweep's report layout: the first run's `report` node over DEFAULT_REPORT."""
    node = next((c["report"] for c in configs if isinstance(c.get("report"), dict)), {})
    layout = {**DEFAULT_REPORT, **node}
    layout["plots"] = [p for p in layout.get("plots") or [] if isinstance(p, dict)]
    return layout


def collect_runs(root: str | Path) -> pd.DataFrame:
    """One row per run directory below `root` (and per job in `jobs.json` without one): job, dir,
    status, error, overrides, `setting` (the row label), the lead, differing and pooled config
    keys (dotted paths, values as written), then the run's numeric final metrics."""
    rows, configs, flats, choices = [], [], [], []
    for run in _run_dirs(Path(root)):
        cfg = _read_yaml(run / ".hydra" / "config.yaml")
        cfg = cfg if isinstance(cfg, dict) else {}
        overrides = _read_yaml(run / ".hydra" / "overrides.yaml")
        overrides = [str(o) for o in overrides] if isinstance(overrides, list) else []
        metrics = read_json(run / "metrics.json") or {}
        status = read_json(run / "status.json") or {}
        state = status.get("status") or ("COMPLETED" if metrics else "INCOMPLETE")
        rows.append(
            {
                "job": run.name,
                "dir": str(run),
                "status": state,
                "error": status.get("error"),  # INTERRUPTED: the signal, epoch, resume command
                "overrides": " ".join(overrides),
                **{k: v for k, v in metrics.items() if isinstance(v, (int, float))},
            }
        )
        configs.append(cfg)
        flats.append(
            {k: v for k, v in _flatten(cfg).items() if k.split(".")[0] not in NOT_SETTINGS}
        )
        choices.append(_choices(run, overrides))
    layout = _layout(configs)
    columns, labels = _settings(flats, choices, layout)
    for row, values, label in zip(rows, columns, labels, strict=True):
        row.update({k: v for k, v in values.items() if k not in row}, setting=label)
    frame = pd.DataFrame(rows + _unstarted_jobs(Path(root), {row["job"] for row in rows}))
    frame.attrs["layout"] = layout
    return frame


def _settings(
    flats: list[dict[str, Any]], choices: list[dict[str, str]], layout: dict[str, Any]
) -> tuple[list[dict[str, Any]], list[str]]:
    """Per run: its config columns ({key: value} of the lead, differing and pooled keys) and its
    setting label (the lead's value, then `group=choice` or `key=value` of each other differing
    key that is neither pooled nor a box plot's x)."""
    lead, pooled = str(layout.get("lead") or ""), set(layout.get("pooled") or [])
    axes = {str(p["x"]) for p in layout["plots"] if p.get("kind") == "box" and p.get("x")}
    keys = sorted({k for flat in flats for k in flat})
    differ = [k for k in keys if len({repr(f.get(k, _MISSING)) for f in flats}) > 1]
    shown = [k for k in keys if k == lead or k in pooled or k in differ]
    lead_node = lead.split(".")[0]
    columns, labels = [], []
    for flat, chosen in zip(flats, choices, strict=True):
        columns.append({k: _cell(flat.get(k)) for k in shown})
        parts = [str(_cell(flat[lead]))] if lead in flat else []
        for key in differ:
            node = key.split(".")[0]
            if key in pooled or key in axes or node == lead_node:
                continue
            part = (
                f"{node}={chosen[node]}"
                if node in chosen
                else f"{key}={_cell(flat.get(key, _MISSING))}"
            )
            if part not in parts:
                parts.append(part)
        labels.append(" ".join(parts) or "all")
    return columns, labels


def _unstarted_jobs(root: Path, seen: set[str]) -> list[dict[str, Any]]:
    """Rows for the jobs that `<root>/jobs.json` lists but that have no run directory (yet): those
    that never ran (PENDING), or died before Hydra wrote their config."""
    summary = read_json(root / "jobs.json") or {}
    rows = []
    for job in summary.get("jobs", []):
        name = Path(job["dir"]).name if job.get("dir") else str(job.get("num"))
        if name in seen:
            continue
        rows.append(
            {
                "job": name,
                "dir": job.get("dir"),
                "status": job.get("status", "PENDING"),
                "error": job.get("error") or "never ran",
                "overrides": " ".join(job.get("overrides") or []),
            }
        )
    return rows


def _percentile_table(done: pd.DataFrame) -> str:
    lines = [
        "| setting | trials | test err mean: p10 | median | p90 | median of per-run medians |",
        "|---|---|---|---|---|---|",
    ]
    for setting in setting_order(done):
        errs = done.loc[done["setting"] == setting, "test/err_mean"].to_numpy(dtype=float)
        meds = done.loc[done["setting"] == setting, "test/err_median"].to_numpy(dtype=float)
        p10, p50, p90 = np.percentile(errs, [10, 50, 90])
        lines.append(
            f"| {setting} | {len(errs)} | {p10:.3f} | {p50:.3f} | {p90:.3f} | "
            f"{np.median(meds):.3f} |"
        )
    return "\n".join(lines)


def _ood_table(done: pd.DataFrame, lead: str) -> pd.DataFrame | None:
    """Table I rows of every completed run that has an `ood.csv` (OOD evaluation), each named by
    its `lead` value (the head's name)."""
    rows = []
    for _, run in done.iterrows():
        path = Path(run["dir"]) / "ood.csv"
        if path.is_file():
            frame = pd.read_csv(path)
            rows += [{"job": run["job"], **row} for row in table_rows(run[lead], frame)]
    return pd.DataFrame(rows) if rows else None


def _ood_note() -> str:
    return (
        "Per job: the head unfiltered, then with each OOD score at its Table I quantile. clean: "
        "the test set; corrupted: the same with its OOD part (erased pairs, or unseen scenes) "
        "included. Errors are mean degrees over the kept pairs; precision and recall are of "
        "keeping in-distribution pairs; each job's ood.md has every quantile."
    )


def make_report(root: str | Path, out: str | Path | None = None) -> dict[str, Path]:
    """Write summary.csv, report.md and the plots for the sweep (or run) directory `root`.

    Raises:
        FileNotFoundError: `root` holds no run directories.
    """
    root = Path(root)
    out = Path(out) if out is not None else root
    runs = collect_runs(root)
    if runs.empty:
        raise FileNotFoundError(f"no runs under {root} (no */.hydra/config.yaml)")
    out.mkdir(parents=True, exist_ok=True)
    files = {"summary": write_text_atomic(out / "summary.csv", runs.to_csv(index=False))}
    done = runs[(runs["status"] == "COMPLETED") & runs.get("test/err_mean", pd.Series()).notna()]
    failed = runs[runs["status"] != "COMPLETED"]
    others = ", ".join(
        f"{n} {status.lower()}" for status, n in failed["status"].value_counts().items()
    )
    md = [
        f"# Report: {root}",
        "",
        f"{len(runs)} jobs: {len(done)} completed" + (f", {others}" if others else "") + ".",
        "",
    ]
    layout = runs.attrs["layout"]
    if not done.empty:
        md += ["## Final test error (degrees), over trials", "", _percentile_table(done), ""]
        plot_files, plot_md = draw_plots(done, layout, out)
        files.update(plot_files)
        md += plot_md
    lead = layout.get("lead")
    ood = _ood_table(done, lead) if lead in done else None
    if ood is not None:
        files["ood_table"] = write_text_atomic(out / "ood_table.csv", ood.to_csv(index=False))
        md += ["## OOD rejection (paper Table I)", "", _ood_note(), "",
               markdown_table(ood.to_dict("records"), ["job", *TABLE_COLUMNS]), ""]  # fmt: skip
    if not failed.empty:
        md += ["## Failed, interrupted or never-run jobs", "",
               "PENDING: never ran; RUNNING: started, never finished (killed); INTERRUPTED: "
               "stopped by a signal, resumable with the command shown.", "",
               "| job | status | overrides | error |",
               "|---|---|---|---|"]  # fmt: skip
        for _, row in failed.iterrows():
            md.append(f"| {row['job']} | {row['status']} | {row['overrides']} | {row['error']} |")
        md.append("")
    files["report"] = write_text_atomic(out / "report.md", "\n".join(md))
    return files


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="rotlearn-report",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("sweep_dir", help="a multirun directory (or a single run directory)")
    parser.add_argument("--out", help="where to write (default: the sweep directory)")
    args = parser.parse_args(argv)
    try:
        files = make_report(args.sweep_dir, args.out)
    except FileNotFoundError as exc:
        print(f"rotlearn-report: {exc}", file=sys.stderr)
        return 2
    for name, path in files.items():
        print(f"{name:12s} {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
