"""`rotlearn-report <sweep dir> [<sweep dir> ...]`: tables and plots of a sweep (or of several,
pooled into one report, e.g. a sweep and a run beside it), made from its run directories alone.

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
        - {kind: ood}                 # OOD figures of runs with ood_samples.csv (Fig. 6c, 8)
      ood:                            # the OOD section (runs with an ood.csv)
        quantiles: [0.5, 0.75, 1.0]   # the q rows of its per-score table
        sets: {clean: test, indoor: test + indoor}   # set names as shown (Fig. 8 analogue)
      paper:                          # the paper's Table I rows, shown beside ours
        source: "Table I, sequence 00"
        where: {loss: chordal}        # our runs comparable to the paper's (config group choices)
        rows: [{rep: a, score: dt, clean_err: 0.12, clean_kept: 69.5, corrupted_err: 0.12,
                corrupted_kept: 37.3, precision: 99.0}, ...]

Writes into the sweep directory (or --out): `summary.csv` (one row per job, failed, interrupted and
never-run ones too, with the differing and pooled config keys), `report.md` (per-setting
percentiles of the final test error over trials; per box plot, the median test error per x value;
OOD Table I rows of runs with an `ood.csv`, beside the paper's when the layout has `paper`, every
score's AUROC, precision, kept % and kept error per test set and quantile, and the error per test
set (paper Fig. 8); the jobs that failed, were interrupted or never ran: those listed PENDING in
the sweep's jobs.json), a `curves` plot (`curves.png`: per-epoch median over trials with a 10-90 %
band per setting, one panel per metric), a `box` plot (`<label>_box.png`: box plots of log10
per-sample test error, `test_errors.json`, per x value and setting) and the `ood` figures
(`rotlearn.cli.report_plots.draw_ood`). Runs with belief metrics in their metrics.json (test/nll,
test/ece, test/coverage_<alpha>, test/<score>_spearman, test/<score>_auroc_noisiest; issue 17) get
a beliefs table per setting and the reliability diagram `reliability.png`
(`rotlearn.cli.report_plots.draw_beliefs`), without a plot declaration.
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

from rotlearn.cli.report_plots import draw_beliefs, draw_ood, draw_plots, setting_order
from rotlearn.io import read_json, read_table, read_yaml, write_text_atomic
from rotlearn.ood.report import LABELS, TABLE_COLUMNS, markdown_table, table_rows

__all__ = ["DEFAULT_REPORT", "collect_runs", "main", "make_report"]

log = logging.getLogger("rotlearn")
DEFAULT_REPORT: dict[str, Any] = {
    "lead": "rep.name",
    "pooled": ["trial", "seed", "data.seed", "optim.lr"],
    "plots": [{"kind": "curves"}],
}
NOT_SETTINGS = ("hydra", "paths", "report")  # per-run paths, and the report layout itself
_MISSING = "-"


def _read_yaml(path: Path, kind: str = "YAML config") -> Any:
    """Plain data of a YAML file of a run (never resolved, no tags, no aliases, size-capped:
    `rotlearn.io.read_yaml`); None if missing or refused (a warning names the file)."""
    try:
        return read_yaml(path, kind, root=path.parent.parent)
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        log.warning("%s (ignored)", exc)
        return None


def _mapping(path: Path) -> dict[str, Any]:
    """A JSON record of a run as a dict: {} where it is missing, refused or not an object."""
    data = read_json(path, root=path.parent)
    if data is not None and not isinstance(data, dict):
        log.warning("%s: not a JSON object (ignored)", path)
    return data if isinstance(data, dict) else {}


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


def _roots(root: str | Path | list[str | Path]) -> list[Path]:
    return [Path(r) for r in root] if isinstance(root, (list, tuple)) else [Path(root)]


def collect_runs(root: str | Path | list[str | Path]) -> pd.DataFrame:
    """One row per run directory below `root` (one sweep or run directory, or a list of them,
    pooled) and per job in a `jobs.json` without one: job (`<sweep name>/<job>` when several
    roots), dir, status, error, overrides, `setting` (the row label), the lead, differing and
    pooled config keys (dotted paths, values as written), `group:<name>` (each config group's
    choice), then the run's numeric final metrics."""
    roots = _roots(root)
    runs = [(r, run) for r in roots for run in _run_dirs(r)]
    rows, configs, flats, choices = [], [], [], []
    for sweep, run in runs:
        cfg = _read_yaml(run / ".hydra" / "config.yaml")
        cfg = cfg if isinstance(cfg, dict) else {}
        overrides = _read_yaml(run / ".hydra" / "overrides.yaml", "overrides file")
        overrides = [str(o) for o in overrides] if isinstance(overrides, list) else []
        metrics = _mapping(run / "metrics.json")
        status = _mapping(run / "status.json")
        state = status.get("status") or ("COMPLETED" if metrics else "INCOMPLETE")
        rows.append(
            {
                "job": _job_name(sweep, run, roots),
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
    return frame


def _job_name(sweep: Path, run: Path, roots: list[Path]) -> str:
    """A run's name in the report: its directory's name, `<sweep>/<run>` when pooling roots."""
    if len(roots) == 1:
        return run.name
    return f"{sweep.name}/{run.name}" if run != sweep else sweep.name


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
    jobs = _mapping(root / "jobs.json").get("jobs")
    rows = []
    for job in jobs if isinstance(jobs, list) else []:
        if not isinstance(job, dict):
            continue
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


def _ood_frames(done: pd.DataFrame) -> list[tuple[pd.Series, pd.DataFrame]]:
    """(run row, its ood.csv) of every completed run that has one."""
    frames = []
    for _, run in done.iterrows():
        path = Path(run["dir"]) / "ood.csv"
        if path.is_file():
            frames.append((run, read_table(path, root=Path(run["dir"]))))
    return frames


def _ood_table(frames: list[tuple[pd.Series, pd.DataFrame]]) -> pd.DataFrame | None:
    """Table I rows of every run with an `ood.csv`, each named by its setting label (the head's
    name, and what else differs, e.g. loss=bingham), with its head (rep) and score."""
    rows = []
    for run, frame in frames:
        rep = str(frame["rep"].iloc[0]) if "rep" in frame and len(frame) else str(run["setting"])
        scores = [None, *frame[frame["in_table"]]["score"].unique()]
        for score, row in zip(scores, table_rows(str(run["setting"]), frame), strict=True):
            groups = {k: run[k] for k in run.index if str(k).startswith("group:")}
            rows.append({"job": run["job"], "rep": rep, "score": score or "", **row, **groups})
    return pd.DataFrame(rows) if rows else None


def _ood_note() -> str:
    return (
        "Per job: the head unfiltered, then with each OOD score at its Table I quantile. clean: "
        "the test set; corrupted: the same with its OOD part (erased pairs, or unseen scenes) "
        "included. Errors are mean degrees over the kept pairs; precision (kept pairs that are "
        "clean) and recall (clean pairs kept) are of keeping in-distribution pairs; AUROC of "
        "the score for telling OOD pairs from clean ones (1 perfect, 0.5 chance, below 0.5 "
        "inverted). Each job's ood.md has every quantile."
    )


PAPER_COLUMNS = [("clean err (deg)", "clean_err"), ("clean kept %", "clean_kept"),
                 ("corrupted err (deg)", "corrupted_err"), ("corrupted kept %", "corrupted_kept"),
                 ("precision %", "precision")]  # fmt: skip


def paper_table(ood: pd.DataFrame, paper: Mapping[str, Any]) -> str:
    """Our Table I rows beside the paper's: for each paper row ({rep, score (absent: the head
    alone), clean_err, clean_kept, corrupted_err, corrupted_kept, precision}), the first of our
    rows with that head and score among the runs matching `paper.where` ({group: choice}), each
    number as `ours (paper)`; our rows without a paper row are listed after, as `ours (-)`.
    """
    where = {f"group:{k}": str(v) for k, v in (paper.get("where") or {}).items()}
    comparable = ood
    for key, value in where.items():
        if key in comparable:
            comparable = comparable[comparable[key].astype(str) == value]
    head = ["method", "paper method", *[c for c, _ in PAPER_COLUMNS], "AUROC"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def cell(ours: Any, theirs: Any) -> str:
        ours_text = "-" if ours is None or (isinstance(ours, float) and np.isnan(ours)) else (
            f"{ours:.2f}" if isinstance(ours, (int, float)) else str(ours))  # fmt: skip
        theirs_text = "-" if theirs is None else f"{float(theirs):g}"
        return f"{ours_text} ({theirs_text})"

    used = set()
    for entry in paper.get("rows") or []:
        if not isinstance(entry, Mapping):
            continue
        rep, score = str(entry.get("rep")), str(entry.get("score") or "")
        match = comparable[(comparable["rep"] == rep) & (comparable["score"] == score)]
        ours = match.iloc[0] if len(match) else None
        if ours is not None:
            used.add(ours.name)
        label = rep + (f" + {LABELS.get(score, score)}" if score else "")
        cells = [cell(None if ours is None else ours[c], entry.get(k)) for c, k in PAPER_COLUMNS]
        auroc = "-" if ours is None or np.isnan(ours["AUROC"]) else f"{ours['AUROC']:.2f}"
        method = ours["method"] if ours is not None else "(not run)"
        lines.append(f"| {method} | {entry.get('label', label)} | " + " | ".join(cells)
                     + f" | {auroc} |")  # fmt: skip
    for index, ours in ood.iterrows():
        if index not in used:
            cells = [cell(ours[c], None) for c, _ in PAPER_COLUMNS]
            auroc = "-" if np.isnan(ours["AUROC"]) else f"{ours['AUROC']:.2f}"
            lines.append(f"| {ours['method']} | - | " + " | ".join(cells) + f" | {auroc} |")
    return "\n".join(lines)


def score_table(frames: list[tuple[pd.Series, pd.DataFrame]], quantiles: list[float] | None,
                set_names: Mapping[str, str]) -> str:  # fmt: skip
    """Every score of every run on every flagged test set: AUROC, then per quantile q (those of
    `quantiles` the runs evaluated; None: all) the kept %, the mean and median error of the
    kept pairs, precision and the % of OOD pairs rejected."""
    head = ["method", "set", "AUROC", "q", "kept %", "kept err mean", "kept err median",
            "precision %", "OOD rejected %"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def fmt(value: Any) -> str:
        return "-" if value is None or (isinstance(value, float) and np.isnan(value)) else (
            f"{value:.2f}")  # fmt: skip

    for run, frame in frames:
        for (score, test_set), rows in frame.groupby(["score", "set"], sort=False):
            if quantiles is not None:
                rows = rows[rows["q"].apply(lambda q: any(np.isclose(q, quantiles)))]
            for i, (_, row) in enumerate(rows.iterrows()):
                method = f"{run['setting']} + {LABELS.get(score, score)}" if i == 0 else ""
                shown = set_names.get(test_set, test_set) if i == 0 else ""
                lines.append(
                    f"| {method} | {shown} | {fmt(row['auroc']) if i == 0 else ''} | "
                    f"{row['q']:g} | {fmt(row['kept_pct'])} | {fmt(row['err_mean_kept'])} | "
                    f"{fmt(row['err_median_kept'])} | {fmt(row['precision'])} | "
                    f"{fmt(row.get('ood_rejected'))} |"
                )
    return "\n".join(lines)


def sets_table(frames: list[tuple[pd.Series, pd.DataFrame]], set_names: Mapping[str, str]) -> str:
    """The error per test set (paper Fig. 8): per run, the head unfiltered and with each score
    at its Table I quantile, the mean error of the kept pairs (and kept %) on the clean test
    set and on each extra set (the clean test set plus unseen pairs)."""
    sets = list(dict.fromkeys(s for _, f in frames for s in f["set"]
                              if s != "corrupted"))  # fmt: skip
    head = ["method", *[set_names.get(s, s) for s in sets]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for run, frame in frames:
        table = frame[frame["in_table"]]
        cells = []
        for s in sets:
            rows = frame[frame["set"] == s]
            cells.append(f"{rows['err_mean_all'].iloc[0]:.2f} (100 %)" if len(rows) else "-")
        lines.append(f"| {run['setting']} | " + " | ".join(cells) + " |")
        for score in table["score"].unique():
            cells = []
            for s in sets:
                rows = table[(table["score"] == score) & (table["set"] == s)]
                if len(rows):
                    kept = rows.iloc[0]
                    cells.append(f"{kept['err_mean_kept']:.2f} ({kept['kept_pct']:.0f} %)")
                else:
                    cells.append("-")
            label = f"{run['setting']} + {LABELS.get(score, score)}"
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def make_report(
    root: str | Path | list[str | Path], out: str | Path | None = None
) -> dict[str, Path]:
    """Write summary.csv, report.md and the plots for the sweep (or run) directory `root`, or
    for several pooled into one report (then into `out`, default the first).

    Raises:
        FileNotFoundError: `root` holds no run directories.
    """
    roots = _roots(root)
    out = Path(out) if out is not None else roots[0]
    runs = collect_runs(roots)
    if runs.empty:
        where = ", ".join(str(r) for r in roots)
        raise FileNotFoundError(f"no runs under {where} (no */.hydra/config.yaml)")
    out.mkdir(parents=True, exist_ok=True)
    files = {"summary": write_text_atomic(out / "summary.csv", runs.to_csv(index=False))}
    done = runs[(runs["status"] == "COMPLETED") & runs.get("test/err_mean", pd.Series()).notna()]
    failed = runs[runs["status"] != "COMPLETED"]
    others = ", ".join(
        f"{n} {status.lower()}" for status, n in failed["status"].value_counts().items()
    )
    md = [
        f"# Report: {', '.join(str(r) for r in roots)}",
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
        belief_files, belief_md = draw_beliefs(done, out)
        files.update(belief_files)
        md += belief_md
    frames = _ood_frames(done) if "dir" in done else []
    ood = _ood_table(frames)
    if ood is not None:
        files["ood_table"] = write_text_atomic(out / "ood_table.csv", ood.to_csv(index=False))
        md += ["## OOD rejection (paper Table I)", "", _ood_note(), "",
               markdown_table(ood.to_dict("records"), ["job", *TABLE_COLUMNS]), ""]  # fmt: skip
        md += _ood_sections(frames, ood, layout, done, out, files)
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


def _ood_sections(frames, ood, layout, done, out, files) -> list[str]:
    """The paper comparison, per-score and per-set tables and the OOD figures of report.md."""
    md = []
    options = layout.get("ood") if isinstance(layout.get("ood"), Mapping) else {}
    set_names = {"clean": "test", "corrupted": "test, half erased",
                 **{str(k): str(v) for k, v in (options.get("sets") or {}).items()}}  # fmt: skip
    paper = layout.get("paper")
    if isinstance(paper, Mapping) and paper.get("rows"):
        where = ", ".join(f"{k}={v}" for k, v in (paper.get("where") or {}).items())
        md += [f"### Side by side with the paper ({paper.get('source', 'paper')})", "",
               "Each cell: ours (the paper's). The paper's numbers are on real data at full "
               "size" + (f"; compared: our runs with {where}" if where else "") + ". "
               + str(paper.get("note", "")), "", paper_table(ood, paper), ""]  # fmt: skip
    quantiles = options.get("quantiles")
    quantiles = [float(q) for q in quantiles] if isinstance(quantiles, list) else None
    md += ["## OOD scores on each test set", "",
           "Per head and score: AUROC (OOD vs clean pairs), and at each quantile q of the "
           "training scores the kept %, the mean and median error (deg) of the kept pairs, "
           "precision (kept pairs that are clean) and the % of OOD pairs rejected.", "",
           score_table(frames, quantiles, set_names), ""]  # fmt: skip
    if any(set(f["set"]) - {"clean", "corrupted"} for _, f in frames):
        md += ["## Error per test set (paper Fig. 8)", "",
               "Mean error (deg) of the kept pairs (kept %), each score at its Table I "
               "quantile. Each extra set is the clean test set plus the pairs of scenes not "
               "trained on, which count as OOD.", "",
               sets_table(frames, set_names), ""]  # fmt: skip
    plot_files, plot_md = draw_ood(done, frames, layout, out, set_names)
    files.update(plot_files)
    return md + plot_md


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="rotlearn-report",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "sweep_dir", nargs="+", help="a multirun (or single run) directory; several: pooled"
    )
    parser.add_argument("--out", help="where to write (default: the first sweep directory)")
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
