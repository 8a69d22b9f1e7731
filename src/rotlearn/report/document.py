"""`make_report`: summary.csv, report.md and the figures of a sweep (or of several pooled),
from its run directories alone (`rotlearn.report.runs`), with the tables of
`rotlearn.report.tables` and the figures of `rotlearn.report.figures`.

The layout comes from the sweep's `report` config node (an experiment's or a sweep's, e.g.
`conf/experiment/synthetic_phi_max.yaml`, `conf/sweep/lr.yaml`), over
`rotlearn.report.layout.DEFAULT_REPORT`::

    report:
      lead: rep.name                  # the key whose value starts each setting's label
      trial_keys: [seed, data.seed, trial]   # pooled: runs differing only here are trials
      plots:                          # drawn when the sweep has what they need
        - {kind: curves, metrics: [train/err_mean, val/err_mean]}   # paper Fig. 3
        - {kind: box, x: data.phi_max_deg, label: phi_max}           # paper Fig. 4
      ood:                            # the OOD section (runs with an ood.csv)
        quantiles: [0.5, 0.75, 1.0]   # the q rows of its per-score table
        sets: {clean: test, indoor: test + indoor}   # set names as shown (Fig. 8 analogue)
      paper:                          # the paper's Table I rows, shown beside ours
        source: "Table I, sequence 00"
        where: {loss: chordal}        # our runs comparable to the paper's (config group choices)
        rows: [{rep: a, score: dt, clean_err: 0.12, clean_kept: 69.5, ...}, ...]

Writes into the sweep directory (or `out`): `summary.csv` (one row per job, failed, interrupted
and never-run ones too, with its setting and the grouping and trial config keys), `report.md`
(per setting the percentiles of the final test error over its trials; per box plot the median
test error per x value; the beliefs table and reliability diagram of runs with a belief; the
OOD Table I rows of runs with an `ood.csv`, beside the paper's when the layout has `paper`,
every score's AUROC, precision, kept % and kept error per test set and quantile, the error per
test set (paper Fig. 8); the jobs that failed, were interrupted or never ran), `curves.png`
(per-epoch median over each setting's trials, 10-90 % band), `<label>_box.png` (log10
per-sample test error per x value), `reliability.png` and the OOD figures.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from rotlearn.io import MAX_BYTES, read_json, read_table, sync_folder, write_text_atomic
from rotlearn.paths import CSV_LOG, OOD_EXAMPLES_FILE, TESTED_WEIGHTS, earlier_attempts
from rotlearn.report import figures, tables
from rotlearn.report.runs import RUN_MARKS, collect_runs, label_without
from rotlearn.report.tensorboard import read_curve

__all__ = ["CURVE_METRICS", "make_report"]

log = logging.getLogger("rotlearn")
CURVE_METRICS = ["train/err_mean", "val/err_mean"]
MAX_EARLIER_LOGS = 64  # a resumed run's earlier CSV logs read for its curves (`_curve`)
MAX_EPOCHS = 1_000_000  # epochs of a curve read from a CSV log (a received one's are data)
OUTPUT_FILES = {  # what make_report returns -> the file in the report's folder
    "summary": "summary.csv",
    "report": "report.md",
    "reliability": "reliability.png",
    "ood_table": "ood_table.csv",
    "ood_pr": "ood_pr.png",
    "ood_scatter": "ood_scatter.png",
    "ood_box": "ood_box.png",
    "ood_sets": "ood_sets.png",
}  # and the layout's plots


def make_report(
    root: str | Path | Sequence[str | Path],
    out: str | Path | None = None,
    group_by: Sequence[str] | None = None,
    pool: Sequence[str] = (),
) -> dict[str, Path]:
    """Write summary.csv, report.md and the figures for the sweep (or run) directory `root`, or
    for several pooled into one report (then into `out`, default the first). `group_by` and
    `pool`: as `rotlearn.report.runs.collect_runs`. Returns {what: path} of every file written.

    Raises:
        FileNotFoundError: `root` holds no run directories.
        FileExistsError: a folder stands where a file of the report goes (nothing written).
        ValueError: a run's `report` node is not a layout (`rotlearn.report.layout.layout_of`).
    """
    roots = [Path(r) for r in root] if isinstance(root, (list, tuple)) else [Path(root)]
    for folder in (r for r in roots if not r.is_dir()):
        what = "no such folder" if not folder.exists() else "not a folder"
        raise FileNotFoundError(f"{folder}: {what}; pass a sweep or run directory")
    out = Path(out) if out is not None else roots[0]
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"--out {out}: a file is there; pass a folder (new or existing)")
    runs = collect_runs(roots, group_by=group_by, pool=pool)
    if runs.empty:
        where = ", ".join(str(r) for r in roots)
        marks = ", ".join(f"*/{m}" for m in RUN_MARKS)
        raise FileNotFoundError(f"no runs under {where} (no run directory: {marks})")
    plots = [p["file"] for p in runs.attrs["layout"]["plots"] if "file" in p]
    for name in (*OUTPUT_FILES.values(), *plots):
        if (out / name).is_dir() and not (out / name).is_symlink():
            raise FileExistsError(f"{out / name}: a folder is where the report writes a file; "
                                  "move it away or pass --out")  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".rotlearn-report-", dir=out))  # whole, or not at all
    try:
        files = _write_report(runs, roots, out, stage, group_by, pool)
        for path in sorted(stage.iterdir()):  # complete: every file written moved into place
            os.replace(path, out / path.name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    sync_folder(out)
    return {what: None if path is None else out / path.name for what, path in files.items()}


def _write_report(runs, roots, out: Path, stage: Path, group_by, pool) -> dict[str, Path]:
    """summary.csv, report.md and the figures of `make_report`, written into `stage` (a folder
    inside the report folder `out`, which the report's links are relative to)."""
    files = {
        "summary": write_text_atomic(stage / OUTPUT_FILES["summary"], runs.to_csv(index=False))
    }
    done, recon = (_having(runs, m) for m in ("test/err_mean", "test/recon_mean"))
    completed = runs.loc[done.index.union(recon.index)]  # with a test score
    failed = runs[runs["status"] != "COMPLETED"]
    others = ", ".join(f"{n} {s.lower()}" for s, n in failed["status"].value_counts().items())
    layout = runs.attrs["layout"]
    md = [
        f"# Report: {', '.join(str(r) for r in roots)}",
        "",
        f"{len(runs)} jobs: {len(completed)} completed" + (f", {others}" if others else "") + ".",
        "",
        _grouping_note(completed, runs.attrs.get("grouping") or [], layout, group_by, pool),
        "",
    ]
    if not done.empty:
        md += ["## Final test error (degrees), over trials", "", _weights_tested(done), "",
               *_diverged(done), tables.percentile_table(done), ""]  # fmt: skip
        md += _plots(done, runs, layout, stage, files)
        md += _beliefs(done, stage, files)
    if not recon.empty:  # auto-encoders (the OOD baseline): their test score
        table = tables.percentile_table(recon, "test/recon_mean", None, "test L1 mean")
        md += ["## Final test reconstruction error (mean L1 per pixel), over trials", "", table, ""]
    frames = _ood_frames(done)
    if frames:
        md += _ood_sections(frames, layout, stage, files, out)
    if not failed.empty:
        md += ["## Failed, interrupted or never-run jobs", "",
               "PENDING: never ran; RUNNING: started, never finished (killed); INTERRUPTED: "
               "stopped by a signal, resumable with the command shown; NOT READ: its folder "
               "leads out of the sweep (a link), so the report did not read it.", "",
               tables.failed_table(failed), ""]  # fmt: skip
    files["report"] = write_text_atomic(stage / OUTPUT_FILES["report"], "\n".join(md))
    return files


def _weights_tested(done: pd.DataFrame) -> str:
    """Which weights the runs' test scores are of (`test_ckpt`), e.g. "Weights tested: the last
    epoch's (4 runs)."."""
    tested = done.get("tested_weights", pd.Series(index=done.index, dtype=object)).astype(object)
    counts = tested.where(tested.notna(), "not recorded").value_counts()
    said = [f"{TESTED_WEIGHTS.get(name, name)} ({n} run{'s' * (n != 1)})"
            for name, n in counts.items()]  # fmt: skip
    return f"Weights tested: {', '.join(said)} (test_ckpt)."


def _diverged(done: pd.DataFrame) -> list[str]:
    """A line naming the runs whose metrics.json says `diverged` (their errors are in the
    table, which they may lift), and a blank line; none where no run did."""
    flagged = done["job"][done.get("diverged", pd.Series(False, index=done.index)).eq(True)]
    if flagged.empty:
        return []
    jobs = ", ".join(map(str, flagged))
    return [f"Diverged ({len(flagged)} of {len(done)}: test error above predicting the identity's,"
            f" or a training loss that blew up; in the table): {jobs}.", ""]  # fmt: skip


def _having(runs: pd.DataFrame, metric: str) -> pd.DataFrame:
    """The completed runs that recorded `metric`."""
    if metric not in runs:
        return runs.iloc[:0]
    return runs[(runs["status"] == "COMPLETED") & runs[metric].notna()]


def _grouping_note(done: pd.DataFrame, grouping: list[str], layout: Mapping[str, Any], group_by,
                   pool) -> str:  # fmt: skip
    """How the completed runs were grouped, and how to group them otherwise."""
    settings = tables.setting_order(done)
    if group_by is not None:
        rule = f"grouped by {', '.join(group_by)} (--group-by)"
    else:
        trial = [*layout["trial_keys"], *pool]
        rule = (
            "grouped by every config key that differs between the runs"
            + (f", except the trial keys {', '.join(trial)}" if trial else "")
            + (" (--pool)" if pool else "")
        )
    keys = ", ".join(grouping) if grouping else "none differ"
    return (
        f"{len(settings)} setting(s) of completed runs, {tables.markdown_text(rule)}: "
        f"{tables.markdown_text(keys)}. Other groupings: "
        "rotlearn-report"
        " --group-by KEY ... or --pool KEY ..."
    )


# ---------------------------------------------------------------------------------- plots


def _csv_logs(run: Path) -> list[Path]:
    """The run's `CSV_LOG` files, the earlier attempts' first (`earlier_attempts`, kept by each
    resume, in n's order; the latest `MAX_EARLIER_LOGS` of them), then its own."""
    try:
        earlier = earlier_attempts(run)
    except OSError:
        earlier = []
    logs = [p / CSV_LOG for p in earlier[-MAX_EARLIER_LOGS:]] + [run / CSV_LOG]
    return [log for log in logs if os.path.lexists(log)]


def _curve(run: Path, key: str) -> np.ndarray | None:
    """Per-epoch values of a metric, index i the value after epoch i + 1 (NaN where no log has
    that epoch: a gap in the curve), from the run's CSV logs (`_csv_logs`; an epoch logged
    again keeps its last attempt's value; the logs read newest first, together within one
    log's read bound; epochs that are not integers 0 ... `MAX_EPOCHS` - 1 left out), or else
    its TensorBoard events."""
    frames, budget = [], MAX_BYTES["metrics log"]
    for newer, csv in enumerate(reversed(_csv_logs(run))):
        try:
            size = csv.stat().st_size
            if newer and size > budget:  # the newest alone: read_table's bound, its message
                log.warning("%s and the logs before it: over the read bound of a metrics log "
                            "together (left out)", csv)  # fmt: skip
                break
            budget -= size
            frame = read_table(csv, run, "metrics log", ("epoch", key))  # bounded, in the run
        except (OSError, ValueError, MemoryError) as exc:
            log.warning("%s (ignored)", exc if str(exc) else f"{csv}: {type(exc).__name__}")
            continue
        if key not in frame or "epoch" not in frame or frame.empty:  # a header only: no epoch
            continue
        numeric = [c for c in ("epoch", key) if not pd.api.types.is_numeric_dtype(frame[c])]
        if numeric:
            log.warning("%s: column %s is not numeric (ignored)", csv, numeric[0])
            continue
        epoch = frame["epoch"]
        whole = (epoch >= 0) & (epoch < MAX_EPOCHS) & (epoch == epoch.round())
        if not whole.all():
            log.warning("%s: %d row(s) whose epoch is no integer in [0, %d) left out", csv,
                        int((~whole).sum()), MAX_EPOCHS)  # fmt: skip
        kept = frame[whole].dropna(subset=[key])
        frames.append(kept.groupby(kept["epoch"].astype(np.int64))[key].last())
    if not frames:
        return read_curve(run, key)
    values = pd.concat(frames[::-1])  # oldest first: the last attempt's value of an epoch wins
    values = values.groupby(level=0).last()
    return values.reindex(range(int(values.index.max()) + 1)).to_numpy(dtype=float)


def _curves(runs: pd.DataFrame, metric: str) -> list[np.ndarray]:
    return [c for c in (_curve(Path(d), metric) for d in runs["dir"]) if c is not None]


def _metric_title(metric: str) -> str:
    """A panel's title: "train/err_mean" -> "train: mean error (deg)"."""
    stage, _, name = metric.partition("/")
    if name.startswith("err_"):
        stat = {"p10": "10th percentile", "p90": "90th percentile"}.get(name[4:], name[4:])
        return f"{stage}: {stat} error (deg)"
    return metric


def _label(plot: Mapping[str, Any]) -> str:
    return str(plot.get("label") or str(plot["x"]).split(".")[-1])


def _plots(done, runs, layout, out: Path, files: dict[str, Path]) -> list[str]:
    """The layout's plots the sweep has data for; report.md lines. A box plot needs its x key
    to take two or more values among the completed runs."""
    md, curves = [], []
    for plot in layout["plots"]:
        kind = plot.get("kind")
        if kind == "box" and plot.get("x") in done and done[plot["x"]].nunique() > 1:
            x, label = str(plot["x"]), _label(plot)
            name = plot["file"]  # a plain name (`rotlearn.report.layout.layout_of`)
            done = done[done[x].notna()]
            done = done.assign(series=label_without(runs.loc[done.index], [x]))
            rows, values = tables.setting_order(done, "series"), _sorted(done[x])
            md += [f"## Median test error (degrees) per {tables.markdown_text(label)}", "",
                   tables.box_table(done, x, label, rows, values), ""]  # fmt: skip
            groups = {
                row: {v: _errors(done[(done["series"] == row) & (done[x] == v)]) for v in values}
                for row in rows
            }
            fig = figures.error_boxes_figure(groups, label)
            if fig is not None:
                files[Path(name).stem] = figures.save_figure(fig, out / name, dpi=110)
                md += [f"![log10 test error per {tables.markdown_text(label)}]({name})", ""]
        elif kind == "curves":
            name = plot["file"]
            metrics = [str(t) for t in plot.get("metrics") or CURVE_METRICS]
            panels = {
                _metric_title(metric): {
                    setting: _curves(done[done["setting"] == setting], metric)
                    for setting in tables.setting_order(done)
                }
                for metric in metrics
            }
            fig = figures.curves_figure(panels)
            if fig is not None:
                files[Path(name).stem] = figures.save_figure(fig, out / name, dpi=110)
                curves += [f"![per-epoch error]({name})", ""]
        elif kind not in ("box", "curves", "ood"):
            log.warning("report: unknown plot kind %r (expected curves or box); skipped", kind)
    if curves:
        md += ["## Error per epoch", "", "Median over each setting's runs (10-90 % band).", ""]
        md += curves
    return md


def _errors(runs: pd.DataFrame) -> np.ndarray:
    """The per-sample test errors of runs (`test_errors.json`), pooled."""
    errors: list[float] = []
    for d in runs["dir"]:
        values = read_json(Path(d) / "test_errors.json", root=d)
        if isinstance(values, list):
            errors.extend(float(v) for v in values if isinstance(v, (int, float)))
    return np.asarray(errors, dtype=float)


def _sorted(values) -> list[Any]:
    values = list(dict.fromkeys(values))
    try:
        return sorted(values)
    except TypeError:
        return sorted(values, key=str)


# ---------------------------------------------------------------------------------- beliefs


def _coverage_columns(done: pd.DataFrame, prefix: str) -> list[tuple[float, str]]:
    """(alpha, column) of the `<prefix>coverage_<alpha>` metrics of the runs, by alpha."""
    found = []
    for column in done.columns:
        name = str(column)
        if name.startswith(f"{prefix}coverage_"):
            try:
                found.append((float(name.rsplit("_", 1)[1]), name))
            except ValueError:
                continue
    return sorted(found)


def _score_order() -> list[str]:
    from rotlearn.scores import SCORES

    return list(SCORES)


def _beliefs(done: pd.DataFrame, out: Path, files: dict[str, Path]) -> list[str]:
    """The beliefs section, for runs whose metrics.json has belief or uncertainty metrics: a
    table per setting (the median over its runs) and the reliability diagram."""
    order = _score_order()
    columns = tables.BELIEF_COLUMNS[1:] + tables.score_columns(done, order)
    keys = [c for c, _ in columns if c in done]
    keys += [c for _, c in _coverage_columns(done, "test/")]
    if not keys:
        return []
    rows = [s for s in tables.setting_order(done)
            if done.loc[done["setting"] == s, keys].notna().any().any()]  # fmt: skip
    if not rows:
        return []
    noisiest = any(k.endswith("_auroc_noisiest") for k in keys)  # data with a noise level only
    md = ["## Beliefs: likelihood, calibration and uncertainty scores", "",
          "Per setting, the median over its runs. NLL: mean negative log-likelihood of the test "
          "targets in nats, w.r.t. the uniform probability measure on SO(3) (lower is better). "
          "ECE: mean |coverage - alpha| of the highest-density credible regions at alpha = "
          "0.1 ... 0.9 (0: calibrated). T: the fitted belief temperature (A -> A / T); at T = 1: "
          "the belief before it. Spearman: rank correlation of each uncertainty score with the "
          "error (dt: positive is good; eigengap and raw_norm: negative is good)."
          + (" AUROC noisiest: how well the score flags the noisiest tenth of the test samples "
             "(1 perfect, 0.5 chance)." if noisiest else ""),
          "", tables.beliefs_table(done, rows, order), ""]  # fmt: skip
    curves, remedies = _reliability_curves(done)
    if curves:
        said = "\n".join(f"{setting}: {remedy}" for setting, remedy in remedies)
        fig = figures.reliability_figure(curves, remedy=said or None)
        files["reliability"] = figures.save_figure(fig, out / OUTPUT_FILES["reliability"])
        md += ["Reliability of the credible regions (coverage against level; on the diagonal: "
               "calibrated, below it: over-confident, above it: too wide):", "",
               f"![reliability diagram]({OUTPUT_FILES['reliability']})", ""]  # fmt: skip
        md += [f"- {tables.markdown_text(setting)}: {remedy}" for setting, remedy in remedies]
        md += [""] if remedies else []
    return md


def _reliability_curves(
    done: pd.DataFrame,
) -> tuple[list[dict[str, Any]], list[tuple[str, str]]]:
    """Coverage against level of each setting (mean over its runs), the untempered belief
    dashed in the same colour; and what to do about each uncalibrated setting (setting,
    remedy)."""
    curves, remedies = [], []
    for i, setting in enumerate(tables.setting_order(done)):
        runs = done[done["setting"] == setting]
        tempered = "test/temperature" in runs and runs["test/temperature"].notna().any()
        for prefix, dashed in (("test/", False), ("test/uncalibrated_", True)):
            columns = [(a, c) for a, c in _coverage_columns(runs, prefix) if runs[c].notna().any()]
            if not columns:
                continue
            ece = pd.to_numeric(runs.get(f"{prefix}ece", pd.Series(dtype=float)), errors="coerce")
            n = int(runs[columns[0][1]].notna().sum())
            mean_ece = float(ece.mean()) if ece.notna().any() else None
            curves.append({
                "label": f"{setting}{' at T = 1' if dashed else ''}"
                         + (f" (mean of {n})" if n > 1 else ""),
                "alphas": [a for a, _ in columns],
                "coverage": [float(runs[c].mean()) for _, c in columns],
                "ece": mean_ece,
                "color": f"C{i % 10}",
                "dashed": dashed,
            })  # fmt: skip
            if not dashed:
                choices = {k[6:]: v for k, v in runs.iloc[0].items() if str(k).startswith("group:")}
                loss = str(choices.get("loss", ""))
                remedy = figures.calibration_remedy(
                    mean_ece, bool(tempered), loss in ("bingham", "fisher_nll"), choices.get("rep")
                )
                if remedy:
                    remedies.append((str(setting), remedy))
    return curves, remedies


# ---------------------------------------------------------------------------------- OOD


OOD_COLUMNS = (
    "score",
    "set",
    "in_table",
    "q",
    "kept_pct",
    "err_mean_all",
    "err_mean_kept",
    "err_median_kept",
    "precision",
    "recall",
    "auroc",
)  # what the report reads (numbers from q on)


def _ood_frames(done: pd.DataFrame) -> list[tuple[pd.Series, pd.DataFrame]]:
    """(run row, its ood.csv) of every completed run that has a readable one: `OOD_COLUMNS`
    (in_table true or false, the others from q on numbers; score and set read as text)."""
    frames = []
    for _, run in done.iterrows():
        path = Path(run["dir"]) / "ood.csv"
        if os.path.lexists(path):
            try:
                frames.append((run, _ood_table_file(path, run["dir"])))
            except (OSError, ValueError) as exc:
                log.warning("report: %s unreadable (%s); skipped", path, exc)
    return frames


def _ood_table_file(path: Path, run_dir: str) -> pd.DataFrame:
    """A run's ood.csv, read bounded, its `OOD_COLUMNS` checked.

    Raises:
        ValueError: the columns missing, or the first one not of its kind.
    """
    frame = read_table(path, root=run_dir)
    if missing := [c for c in OOD_COLUMNS if c not in frame]:
        raise ValueError(f"not an OOD table (no column {', '.join(missing)})")
    if not pd.api.types.is_bool_dtype(frame["in_table"]):
        raise ValueError("column in_table is not true / false")
    for column in OOD_COLUMNS[3:]:
        if not pd.api.types.is_numeric_dtype(frame[column]):
            raise ValueError(f"column {column} is not numeric")
    return frame.astype({"score": str, "set": str})


def _oracle_frame(run: pd.Series, frame: pd.DataFrame, sets: dict | None) -> pd.DataFrame:
    """`frame` with the rows of an oracle whose score is each pair's own error, at the Table I
    quantile of the run's DT (else of its first score), thresholds from the same reference set,
    from the run's samples (`sets`: `_samples`; `frame` as it is without them, or warned where
    they give no threshold)."""
    from rotlearn.ood.evaluation import reference_set, rejection_table
    from rotlearn.scores import Score

    table, reference = frame[frame["in_table"]], reference_set(frame)
    if not len(table) or sets is None or reference not in sets:
        return frame
    if "corrupted" not in sets.get("corrupted", {}):
        return frame
    dt = table[table["score"] == "dt"]
    oracle = Score(tables.ORACLE, True, None, description="the pair's own error (deg)")
    try:
        q = float((dt if len(dt) else table)["q"].iloc[0])
        rows = rejection_table(sets, [oracle], [q], {oracle.name: q}, reference)
    except ValueError as exc:  # no finite reference error, a q outside [0, 1]
        log.warning("report: %s: no oracle row (%s)", run["dir"], exc)
        return frame
    return pd.concat([frame, rows[rows["in_table"]]], ignore_index=True)


def _ood_table(frames: list[tuple[pd.Series, pd.DataFrame]], samples: list) -> pd.DataFrame:
    """Table I rows of every run with an `ood.csv`, each named by its setting label, with its
    head (rep), score and config group choices; a run with samples (`samples`, one per run:
    `_samples`) gets a last row for the oracle that rejects by each pair's own error
    (`_oracle_frame`)."""
    rows = []
    for (run, frame), sets in zip(frames, samples, strict=True):
        rep = str(frame["rep"].iloc[0]) if "rep" in frame and len(frame) else str(run["setting"])
        frame = _oracle_frame(run, frame, sets)
        scores = [None, *frame[frame["in_table"]]["score"].unique()]
        rows_one = tables.table_one_rows(str(run["setting"]), frame)
        for score, row in zip(scores, rows_one, strict=True):
            groups = {k: run[k] for k in run.index if str(k).startswith("group:")}
            rows.append({"job": run["job"], "rep": rep, "score": score or "", **row, **groups})
    return pd.DataFrame(rows)


OOD_NOTE = (
    "Per job: the head unfiltered, then with each OOD score at its Table I quantile. clean: "
    "the test set; corrupted: the same with its OOD part (erased pairs, or unseen scenes) "
    "included. Errors are mean degrees over the kept pairs; precision (kept pairs that are "
    "clean) and recall (clean pairs kept) are of keeping in-distribution pairs; AUROC of "
    "the score for telling OOD pairs from clean ones (1 perfect, 0.5 chance, below 0.5 "
    "inverted). Each job's ood.md has every quantile. + own error (oracle): keeping the pairs "
    "whose own error is below the same quantile of the reference pairs' errors, which no score "
    "can know: an uncertainty that tracked the error exactly would reach it; a score above it "
    "flags OOD pairs beyond their error, and a target it misses is out of any such score's reach."
)


def _ood_sections(frames, layout, out: Path, files: dict[str, Path], report: Path) -> list[str]:
    """Table I, the paper comparison, per-score and per-set tables and the OOD figures (written
    into `out`; links to the runs' own images relative to the report's folder `report`)."""
    samples = [_samples(run, frame) for run, frame in frames]
    ood = _ood_table(frames, samples)
    files["ood_table"] = write_text_atomic(out / OUTPUT_FILES["ood_table"], ood.to_csv(index=False))
    md = ["## OOD rejection (paper Table I)", "", OOD_NOTE, "",
          tables.markdown_table(ood, ["job", *tables.TABLE_ONE_COLUMNS]), ""]  # fmt: skip
    if ood["method"].duplicated().any():
        md += ["### Over seeds: mean (min-max)", "",
               "Runs that differ only in their trial keys (seeds: `report.trial_keys`) pooled: "
               "per method the number of runs, and each number's mean and range over them.", "",
               tables.seeds_table(ood), ""]  # fmt: skip
    options = layout.get("ood") if isinstance(layout.get("ood"), Mapping) else {}
    set_names = {"clean": "test", "corrupted": "test, half erased",
                 **{str(k): str(v) for k, v in (options.get("sets") or {}).items()}}  # fmt: skip
    paper = layout.get("paper")
    if isinstance(paper, Mapping) and paper.get("rows"):
        ours = ood[ood["score"] != tables.ORACLE]  # the oracle has no paper row
        where = tables.markdown_text(
            ", ".join(f"{k}={v}" for k, v in (paper.get("where") or {}).items())
        )
        source = tables.markdown_text(paper.get("source", "paper"))
        md += [f"### Side by side with the paper ({source})", "",
               "Each cell: ours (the paper's); ours over a method's runs (seeds) as mean "
               "[min-max], AUROC as mean (min-max). The paper's numbers are on real data at full "
               "size" + (f"; compared: our runs with {where}" if where else "")
               + ". " + tables.markdown_text(paper.get("note", "")), "",
               tables.paper_table(ours, paper), ""]  # fmt: skip
    quantiles = options.get("quantiles")
    quantiles = [float(q) for q in quantiles] if isinstance(quantiles, list) else None
    md += ["## OOD scores on each test set", "",
           "Per head and score: AUROC (OOD vs clean pairs), and at each quantile q of the "
           "reference scores (each run's thresholds_from: validation pairs by default, "
           "training pairs in the paper's protocol) the kept %, the mean and median error "
           "(deg) of the kept pairs, "
           "precision (kept pairs that are clean) and the % of OOD pairs rejected.", "",
           tables.score_table(frames, quantiles, set_names), ""]  # fmt: skip
    if any(set(f["set"]) - {"clean", "corrupted"} for _, f in frames):
        md += ["## Error per test set (paper Fig. 8)", "",
               "Mean error (deg) of the kept pairs (kept %), each score at its Table I "
               "quantile. Each extra set is the clean test set plus the pairs of scenes not "
               "trained on, which count as OOD.", "",
               tables.sets_table(frames, set_names), ""]  # fmt: skip
    return md + _ood_figures(frames, samples, out, set_names, files, report)


def _samples(run: pd.Series, frame: pd.DataFrame) -> dict[str, dict] | None:
    """The sets of the run's `ood_samples.csv` (`rotlearn.ood.records.read_samples`, a file
    inside the run), if they are those its ood.csv (`frame`) was made from: the reference set
    with a column for a score of the table, the test sets with their OOD flags (`ood`); None
    where it has none or it is unreadable (warned, naming the file)."""
    from rotlearn.ood.evaluation import TEST_SETS, reference_set
    from rotlearn.ood.records import SAMPLES_FILE, read_samples
    from rotlearn.scores import SCORES

    path = Path(run["dir"]) / SAMPLES_FILE
    if not os.path.lexists(path):
        return None
    reference = reference_set(frame)
    try:
        sets = read_samples(path, root=run["dir"])
        if "corrupted" not in sets or any(
            "corrupted" not in sets[s] for s in TEST_SETS if s in sets
        ):
            raise ValueError("no set corrupted, or a test set without its ood column")
        if not any(n in SCORES and n in sets.get(reference, {}) for n in frame["score"]):
            raise ValueError(f"no set {reference} with a column for a score of its ood.csv")
    except (ValueError, OSError, pd.errors.ParserError) as exc:
        log.warning("report: %s unreadable (%s); its oracle row and OOD figures are skipped",
                    path, exc)  # fmt: skip
        return None
    return sets


def _ood_samples(frames, samples: list) -> list[tuple[str, dict, list, dict]]:
    """(setting, sets, scores, reference scores) of each run whose `ood_samples.csv` is
    readable (`samples`: `_samples` of each run; the reference: the set its thresholds come
    from)."""
    from rotlearn.ood.evaluation import reference_set
    from rotlearn.scores import SCORES

    runs = []
    for (run, frame), sets in zip(frames, samples, strict=True):
        if sets is None:
            continue
        reference = sets.get(reference_set(frame), {})
        names = [n for n in dict.fromkeys(frame["score"]) if n in SCORES and n in reference]
        runs.append((str(run["setting"]), sets, [SCORES[n] for n in names], reference))
    return runs


def _mean_curve(curves: list[list[dict[str, Any]]]) -> list[dict[str, float]]:
    """The precision-recall curve of several runs (each `precision_recall_curve` over the same
    quantiles): at each q, the mean recall and the mean precision where it is defined."""
    mean = []
    for rows in zip(*curves, strict=True):
        precision = [r["precision"] for r in rows if not math.isnan(r["precision"])]
        recall = float(np.mean([r["recall"] for r in rows]))
        precision = float(np.mean(precision)) if precision else math.nan
        mean.append({"q": rows[0]["q"], "recall": recall, "precision": precision})
    return mean


def _ood_figures(
    frames, samples: list, out: Path, set_names: Mapping[str, str], files: dict, report: Path
) -> list[str]:
    """Per head and score, from each run's `ood_samples.csv`: precision-recall over q on each
    flagged set but the clean one (`ood_pr.png`), error against score on the half-erased set
    (`ood_scatter.png`), score box plots (`ood_box.png`); the error per test set
    (`ood_sets.png`, when runs have extra sets); each run's `ood_examples.png`, linked."""
    from rotlearn.ood.evaluation import precision_recall_curve

    md: list[str] = []
    runs = _ood_samples(frames, samples)
    if runs:
        flagged = list(dict.fromkeys(n for _, sets, _, _ in runs for n, v in sets.items()
                                     if n != "clean" and "corrupted" in v))  # fmt: skip
        fig, axes = figures.grid(1, len(flagged), size=(5.0, 4.2))
        for ax, name in zip(axes[0], flagged, strict=True):
            pooled: dict[str, list] = {}  # runs of one setting (seeds) share its curve
            for setting, sets, scores, reference in runs:
                for s in (s for s in scores if name in sets):
                    curve = precision_recall_curve(s, reference[s.name], sets[name])
                    label = f"{setting} + {tables.LABELS.get(s.name, s.name)}"
                    pooled.setdefault(label, []).append(curve)
            curves = {label if len(c) == 1 else f"{label} (mean of {len(c)} runs)": _mean_curve(c)
                      for label, c in pooled.items()}  # fmt: skip
            if curves:
                ax.set_visible(True)
                figures.pr_figure(curves, ax=ax, title=set_names.get(name, name))
        files["ood_pr"] = figures.save_figure(fig, out / OUTPUT_FILES["ood_pr"], dpi=90)
        n_cols = max(len(scores) for _, _, scores, _ in runs)
        for key, what in (
            ("ood_scatter", "Error against score on the half-erased test set"),
            ("ood_box", "Score distributions (paper Fig. 6c)"),
        ):
            fig, axes = figures.grid(len(runs), n_cols, size=(4.2, 3.6))
            for row, (setting, sets, scores, _) in enumerate(runs):
                for col, score in enumerate(scores):
                    ax = axes[row][col]
                    ax.set_visible(True)
                    title = f"{setting}: {score.name}"
                    if key == "ood_scatter":
                        data = sets["corrupted"]
                        figures.scatter_figure(score.name, score.keep_below, data["error"],
                                               data[score.name], data["corrupted"], ax=ax,
                                               title=title)  # fmt: skip
                    else:
                        groups = figures.box_groups(score.name, sets)
                        figures.score_boxes_figure(score.name, score.keep_below, groups, ax=ax,
                                                   title=title)  # fmt: skip
            files[key] = figures.save_figure(fig, out / OUTPUT_FILES[key], dpi=90)
            md += [f"### {what}", "", f"![{what}]({OUTPUT_FILES[key]})", ""]
        md = ["### Precision-recall over the quantile q (q = 0.05 to 0.97)", "",
              "Runs of one setting (seeds) share a curve: their mean recall and precision at "
              "each q.", "", f"![precision-recall over q]({OUTPUT_FILES['ood_pr']})", "",
              *md]  # fmt: skip
    bars, sets = _set_bars(frames)
    if len(sets) >= 2 and bars:
        fig = figures.sets_bars_figure(bars, [set_names.get(s, s) for s in sets])
        files["ood_sets"] = figures.save_figure(fig, out / OUTPUT_FILES["ood_sets"], dpi=90)
        md += ["### Error per test set (paper Fig. 8b)", "",
               f"![error per test set]({OUTPUT_FILES['ood_sets']})", ""]  # fmt: skip
    examples = [(run, Path(run["dir"]) / OOD_EXAMPLES_FILE) for run, _ in frames]
    examples = [(run, path) for run, path in examples if path.is_file()]
    if examples:
        md += ["### Example test pairs with their scores", ""]
        for run, path in examples:
            setting = tables.markdown_text(run["setting"])
            md += [f"{setting} (job {tables.markdown_text(run['job'])}):", "",
                   f"![examples {setting}]({os.path.relpath(path, report)})", ""]  # fmt: skip
    return ["## OOD figures", "", *md] if md else []


def _set_bars(frames) -> tuple[dict[str, list[float]], list[str]]:
    """Paper Fig. 8b's bars: per head alone and head + score at its Table I quantile, the mean
    error of the kept pairs on each test set (clean and extra sets)."""
    sets = list(dict.fromkeys(s for _, f in frames for s in f["set"] if s != "corrupted"))
    bars: dict[str, list[float]] = {}
    for run, frame in frames:
        by_set = {s: frame[frame["set"] == s] for s in sets}
        bars[str(run["setting"])] = [
            float(rows["err_mean_all"].iloc[0]) if len(rows) else np.nan for rows in by_set.values()
        ]
        table = frame[frame["in_table"]]
        for score in table["score"].unique():
            label = f"{run['setting']} + {tables.LABELS.get(score, score)}"
            bars[label] = []
            for s in sets:
                rows = table[(table["score"] == score) & (table["set"] == s)]
                bars[label].append(float(rows["err_mean_kept"].iloc[0]) if len(rows) else np.nan)
    return bars, sets
