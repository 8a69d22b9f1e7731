"""The plots and plot tables of `rotlearn-report` (paper Figs. 3 and 4), drawn from run directories.

A plot definition comes from the sweep's `report.plots` (`rotlearn.cli.report`): `{kind: curves,
metrics: [...]}` draws the per-epoch median over each setting's runs with a 10-90 % band;
`{kind: box, x: <config key>, label: ...}` draws box plots of log10 per-sample test error per x
value and setting, with a table of median errors.

`draw_ood` draws the OOD figures of the runs that have an OOD evaluation (`ood.csv`,
`ood_samples.csv`, `ood_examples.png`, written by `rotlearn.ood.OODEvaluation`): precision-recall
over q, error against score, score box plots (paper Fig. 6c), the error per test set (paper
Fig. 8b) and each run's erased example pairs. The figure code per panel is `rotlearn.ood.report`'s.

`draw_beliefs` draws the beliefs section of the runs whose `metrics.json` has belief metrics
(test/nll, test/ece, test/coverage_<alpha>, test/<score>_spearman, ...): a table per setting and
the reliability diagram (`rotlearn.plots.reliability_figure`); no plot declaration is needed.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from rotlearn.io import MAX_BYTES, read_json, read_table

__all__ = ["BELIEF_COLUMNS", "CURVE_METRICS", "draw_beliefs", "draw_ood", "draw_plots",
           "setting_order"]  # fmt: skip

log = logging.getLogger("rotlearn")
CURVE_METRICS = ["train/err_mean", "val/err_mean"]


def _curves(run: Path, tag: str) -> np.ndarray | None:
    """Per-epoch values of a scalar, from the run's CSV log or else its TensorBoard events."""
    csv = run / "csv" / "metrics.csv"
    frame = None
    if os.path.lexists(csv):
        try:
            frame = read_table(csv, root=run)
        except (OSError, ValueError) as exc:
            log.warning("%s (ignored)", exc)
    if frame is not None and tag in frame:
        values = frame.dropna(subset=[tag]).groupby("epoch")[tag].last()
        return values.to_numpy(dtype=float)
    events = run / "tensorboard"
    if events.is_dir() and _readable_events(events, run):
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

        acc = EventAccumulator(str(events), size_guidance={"scalars": 0}).Reload()
        if tag in acc.Tags().get("scalars", []):
            return np.array([e.value for e in acc.Scalars(tag)], dtype=float)
    return None


def _readable_events(folder: Path, run: Path) -> bool:
    """Whether TensorBoard may read the event files in `folder`: regular files inside the run,
    at most `MAX_BYTES["TensorBoard events"]` in all (TensorBoard reads them unbounded; a named
    pipe would hang it). A warning names what is refused."""
    total = 0
    for path in folder.rglob("*"):
        if path.is_dir() and not path.is_symlink():
            continue
        real = Path(os.path.realpath(path))
        if not (path.is_file() and real.is_relative_to(os.path.realpath(run))):
            log.warning("%s: not a regular file inside the run; its events are not read", path)
            return False
        total += path.stat().st_size
    if total > MAX_BYTES["TensorBoard events"]:
        log.warning(
            "%s: over %d bytes of events; not read", folder, MAX_BYTES["TensorBoard events"]
        )
        return False
    return True


def setting_order(done: pd.DataFrame, column: str = "setting") -> list[Any]:
    """The distinct values of `column`, in the order of their first job (the sweep's order)."""
    return list(dict.fromkeys(done[column].dropna()))


def _sorted_values(values) -> list[Any]:
    values = list(dict.fromkeys(values))
    try:
        return sorted(values)
    except TypeError:
        return sorted(values, key=str)


def _label(plot: Mapping[str, Any]) -> str:
    return str(plot.get("label") or str(plot["x"]).split(".")[-1])


def _box_table(done: pd.DataFrame, plot: Mapping[str, Any]) -> str:
    """Median test error per setting (rows) and value of the plot's x (columns)."""
    x, label = str(plot["x"]), _label(plot)
    values = _sorted_values(done[x].dropna())
    head = "| setting | " + " | ".join(f"{label} {v:g}" if isinstance(v, (int, float))
                                      else f"{label} {v}" for v in values) + " |"  # fmt: skip
    lines = [head, "|---|" + "---|" * len(values)]
    for setting in setting_order(done):
        cells = []
        for v in values:
            sel = done[(done["setting"] == setting) & (done[x] == v)]["test/err_median"]
            cells.append(f"{sel.median():.3f}" if len(sel) else "-")
        lines.append(f"| {setting} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _plot_curves(done: pd.DataFrame, plot: Mapping[str, Any], path: Path) -> bool:
    """Per-epoch median over each setting's runs, with a 10-90 % band, one panel per metric."""
    plt = _pyplot()
    tags = [str(t) for t in plot.get("metrics") or CURVE_METRICS]
    fig, axes = plt.subplots(1, len(tags), figsize=(1 + 5 * len(tags), 4), sharey=True,
                             squeeze=False)  # fmt: skip
    drew = False
    for ax, tag in zip(axes[0], tags, strict=True):
        for setting in setting_order(done):
            dirs = done.loc[done["setting"] == setting, "dir"]
            curves = [c for c in (_curves(Path(d), tag) for d in dirs) if c is not None and len(c)]
            if not curves:
                continue
            n = min(len(c) for c in curves)
            p10, p50, p90 = np.percentile(np.stack([c[:n] for c in curves]), [10, 50, 90], axis=0)
            epochs = np.arange(1, n + 1)
            ax.plot(epochs, p50, label=f"{setting} (median of {len(curves)})")
            ax.fill_between(epochs, p10, p90, alpha=0.25)
            drew = True
        ax.set(title=tag, xlabel="epoch", yscale="log")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("error (deg)")
    fig.tight_layout()
    if drew:
        axes[0][-1].legend()
        fig.savefig(path, dpi=110)
    plt.close(fig)
    return drew


def _plot_box(done: pd.DataFrame, plot: Mapping[str, Any], path: Path) -> bool:
    """Box plots of log10 per-sample test error (`test_errors.json`) per x value and setting."""
    plt = _pyplot()
    x = str(plot["x"])
    values, settings = _sorted_values(done[x].dropna()), setting_order(done)
    fig, ax = plt.subplots(figsize=(3 + 2 * len(values), 4))
    width = 0.8 / max(len(settings), 1)
    drew = False
    for i, setting in enumerate(settings):
        data, positions = [], []
        for j, value in enumerate(values):
            errors = []
            for d in done[(done["setting"] == setting) & (done[x] == value)]["dir"]:
                found = read_json(Path(d) / "test_errors.json", root=d)
                if isinstance(found, list) and all(isinstance(e, int | float) for e in found):
                    errors.extend(found)
            if errors:
                data.append(np.log10(np.maximum(errors, 1e-6)))
                positions.append(j + (i - (len(settings) - 1) / 2) * width)
        if data:
            box = ax.boxplot(data, positions=positions, widths=width * 0.9, notch=True,
                             patch_artist=True, showfliers=False)  # fmt: skip
            for patch in box["boxes"]:
                patch.set_facecolor(f"C{i}")
            ax.plot([], [], color=f"C{i}", label=setting, linewidth=8)
            drew = True
    ax.set_xticks(range(len(values)), [f"{v:g}" if isinstance(v, (int, float)) else str(v)
                                       for v in values])  # fmt: skip
    ax.set(xlabel=_label(plot), ylabel="log10 test error (deg)")
    ax.legend()
    ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    if drew:
        fig.savefig(path, dpi=110)
    plt.close(fig)
    return drew


def draw_plots(done: pd.DataFrame, layout: Mapping[str, Any], out: Path) -> tuple[dict, list[str]]:
    """Draw the layout's plots that the sweep has data for: ({file key: path}, report.md lines).
    A box plot needs its x key to take two or more values among the completed runs."""
    files, md, curves = {}, [], []
    for plot in layout["plots"]:
        kind = plot.get("kind")
        if kind == "box" and plot.get("x") in done and done[plot["x"]].nunique() > 1:
            label = _label(plot)
            name = str(plot.get("file") or f"{label}_box.png")
            md += [f"## Median test error (degrees) per {label}", "", _box_table(done, plot), ""]
            if _plot_box(done, plot, out / name):
                files[Path(name).stem] = out / name
                md += [f"![log10 test error per {label}]({name})", ""]
        elif kind == "curves":
            name = str(plot.get("file") or "curves.png")
            if _plot_curves(done, plot, out / name):
                files[Path(name).stem] = out / name
                curves += [f"![per-epoch error]({name})", ""]
        elif kind not in ("box", "curves"):
            log.warning("report: unknown plot kind %r (expected curves or box); skipped", kind)
    if curves:
        md += ["## Error per epoch", "", *curves]
    return files, md


def _ood_samples(frames: list) -> list[tuple[str, dict, list]]:
    """(setting, sets, scores) of each run whose `ood_samples.csv` is readable."""
    from rotlearn.ood.report import SAMPLES_FILE, read_samples
    from rotlearn.ood.scores import SCORES

    runs = []
    for run, frame in frames:
        path = Path(run["dir"]) / SAMPLES_FILE
        if not path.is_file():
            continue
        try:
            sets = read_samples(path)
        except (ValueError, OSError, pd.errors.ParserError) as exc:
            log.warning("report: %s unreadable (%s); its OOD figures are skipped", path, exc)
            continue
        names = [n for n in dict.fromkeys(frame["score"]) if n in SCORES and n in sets["train"]]
        runs.append((str(run["setting"]), sets, [SCORES[n] for n in names]))
    return runs


def _grid(plt, rows: int, cols: int, size=(4.0, 3.2)):
    fig, axes = plt.subplots(rows, cols, figsize=(size[0] * cols, size[1] * rows), squeeze=False)
    for ax in axes.flat:
        ax.set_visible(False)
    return fig, axes


def _save(fig, plt, path: Path) -> Path:
    from rotlearn.ood.report import save_figure

    fig.tight_layout()
    save_figure(fig, path, dpi=90)
    plt.close(fig)
    return path


def _sets_bars(frames: list, set_names: Mapping[str, str], path: Path) -> bool:
    """Paper Fig. 8b: mean error of the kept pairs per test set (clean and extra sets), one bar
    per head alone and head + score at its Table I quantile."""
    from rotlearn.ood.report import LABELS

    plt = _pyplot()
    sets = list(dict.fromkeys(s for _, f in frames for s in f["set"] if s != "corrupted"))
    bars: dict[str, list[float]] = {}
    for run, frame in frames:
        by_set = {s: frame[frame["set"] == s] for s in sets}
        bars[str(run["setting"])] = [
            float(rows["err_mean_all"].iloc[0]) if len(rows) else np.nan for rows in by_set.values()
        ]
        table = frame[frame["in_table"]]
        for score in table["score"].unique():
            label = f"{run['setting']} + {LABELS.get(score, score)}"
            bars[label] = []
            for s in sets:
                rows = table[(table["score"] == score) & (table["set"] == s)]
                bars[label].append(float(rows["err_mean_kept"].iloc[0]) if len(rows) else np.nan)
    if len(sets) < 2 or not bars:
        return False
    fig, ax = plt.subplots(figsize=(2 + 2.2 * len(sets), 4))
    width = 0.8 / len(bars)
    for i, (label, heights) in enumerate(bars.items()):
        x = np.arange(len(sets)) + (i - (len(bars) - 1) / 2) * width
        ax.bar(x, heights, width=width * 0.95, label=label, color=f"C{i % 10}")
    ax.set_xticks(range(len(sets)), [set_names.get(s, s) for s in sets])
    ax.set(ylabel="mean error of kept pairs (deg)")
    ax.legend(fontsize=7)
    ax.grid(True, axis="y", alpha=0.3)
    _save(fig, plt, path)
    return True


def draw_ood(
    done: pd.DataFrame,
    frames: list,
    layout: Mapping[str, Any],
    out: Path,
    set_names: Mapping[str, str] | None = None,
) -> tuple[dict, list[str]]:
    """The OOD figures of the runs in `frames` ((run row, its ood.csv) pairs): ({file key: path},
    report.md lines). Per head and score, from each run's `ood_samples.csv`: precision-recall
    over q on each flagged set but the clean one (`ood_pr.png`), error against score on the
    half-erased set (`ood_scatter.png`), score box plots (`ood_box.png`); the error per test set
    (`ood_sets.png`, when runs have extra sets); each run's `ood_examples.png`, linked."""
    from rotlearn.ood.evaluation import precision_recall_curve
    from rotlearn.ood.report import LABELS, box_figure, pr_figure, scatter_figure

    set_names = dict(set_names or {})
    files: dict[str, Path] = {}
    md: list[str] = []
    plt = _pyplot()
    runs = _ood_samples(frames)
    if runs:
        flagged = list(dict.fromkeys(n for _, sets, _ in runs for n, v in sets.items()
                                     if n != "clean" and "corrupted" in v))  # fmt: skip
        fig, axes = _grid(plt, 1, len(flagged), size=(5.0, 4.0))
        for ax, name in zip(axes[0], flagged, strict=True):
            curves = {}
            for setting, sets, scores in runs:
                for score in scores:
                    if name in sets:
                        curves[f"{setting} + {LABELS.get(score.name, score.name)}"] = (
                            precision_recall_curve(score, sets["train"][score.name], sets[name])
                        )
            if curves:
                ax.set_visible(True)
                first = next(s for _, _, scores in runs for s in scores)
                pr_figure(first, curves, ax=ax, title=f"{set_names.get(name, name)}")
        files["ood_pr"] = _save(fig, plt, out / "ood_pr.png")
        n_cols = max(len(scores) for _, _, scores in runs)
        for key, draw, what in (
            ("ood_scatter", scatter_figure, "Error against score on the half-erased test set"),
            ("ood_box", box_figure, "Score distributions (paper Fig. 6c)"),
        ):
            fig, axes = _grid(plt, len(runs), n_cols)
            for row, (setting, sets, scores) in enumerate(runs):
                for col, score in enumerate(scores):
                    axes[row][col].set_visible(True)
                    draw(score, sets, ax=axes[row][col], title=f"{setting}:\n{score.name}")
            files[key] = _save(fig, plt, out / f"{key}.png")
            md += [f"### {what}", "", f"![{what}]({key}.png)", ""]
        md = ["### Precision-recall over the quantile q (q = 0.05 to 0.97)", "",
              "![precision-recall over q](ood_pr.png)", "", *md]  # fmt: skip
    if _sets_bars(frames, set_names, out / "ood_sets.png"):
        files["ood_sets"] = out / "ood_sets.png"
        md += ["### Error per test set (paper Fig. 8b)", "", "![error per test set](ood_sets.png)",
               ""]  # fmt: skip
    examples = [(run, Path(run["dir"]) / "ood_examples.png") for run, _ in frames]
    examples = [(run, path) for run, path in examples if path.is_file()]
    if examples:
        md += ["### Example test pairs with their scores", ""]
        for run, path in examples:
            md += [f"{run['setting']} (job {run['job']}):", "",
                   f"![examples {run['setting']}]({os.path.relpath(path, out)})", ""]  # fmt: skip
    if md:
        md = ["## OOD figures", "", *md]
    return files, md


# ---------------------------------------------------------------------------------- beliefs

BELIEF_COLUMNS = [("test/err_median", "median err (deg)"), ("test/nll", "NLL (nats)"),
                  ("test/ece", "ECE"), ("test/temperature", "T"),
                  ("test/uncalibrated_nll", "NLL at T = 1"),
                  ("test/uncalibrated_ece", "ECE at T = 1")]  # fmt: skip


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


def _score_columns(done: pd.DataFrame) -> list[tuple[str, str]]:
    """(column, header) of every test/<score>_spearman, then test/<score>_auroc_noisiest, the
    scores in the order of `rotlearn.ood.scores.SCORES` (others after, by name)."""
    from rotlearn.ood.scores import SCORES

    order = {name: i for i, name in enumerate(SCORES)}
    columns = []
    for suffix, what in (("_spearman", "Spearman"), ("_auroc_noisiest", "AUROC noisiest")):
        names = [str(c) for c in done.columns
                 if str(c).startswith("test/") and str(c).endswith(suffix)]  # fmt: skip
        scores = sorted((n[5 : -len(suffix)] for n in names), key=lambda s: (order.get(s, 99), s))
        columns += [(f"test/{score}{suffix}", f"{score} {what}") for score in scores]
    return columns


def _beliefs_table(done: pd.DataFrame, rows: list[Any]) -> str:
    """Per setting: the median over its runs of each belief metric any run has."""
    columns = [(c, h) for c, h in BELIEF_COLUMNS + _score_columns(done)
               if c in done and done[c].notna().any()]  # fmt: skip
    lines = ["| setting | runs | " + " | ".join(h for _, h in columns) + " |",
             "|---|---|" + "---|" * len(columns)]  # fmt: skip
    for setting in rows:
        runs = done[done["setting"] == setting]
        cells = []
        for column, _ in columns:
            values = pd.to_numeric(runs[column], errors="coerce").dropna()
            cells.append(f"{values.median():.3g}" if column == "test/temperature" and len(values)
                         else f"{values.median():.3f}" if len(values) else "-")  # fmt: skip
        lines.append(f"| {setting} | {len(runs)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _reliability(done: pd.DataFrame, path: Path) -> bool:
    """Coverage against credible level of each setting (mean over its runs); the untempered
    belief dashed in the same colour where the runs were tempered."""
    from rotlearn.ood.report import save_figure
    from rotlearn.plots import reliability_figure

    curves = []
    for i, setting in enumerate(setting_order(done)):
        runs = done[done["setting"] == setting]
        for prefix, dashed in (("test/", False), ("test/uncalibrated_", True)):
            columns = [(a, c) for a, c in _coverage_columns(runs, prefix) if runs[c].notna().any()]
            if not columns:
                continue
            ece = runs[f"{prefix}ece"] if f"{prefix}ece" in runs else pd.Series(dtype=float)
            ece = pd.to_numeric(ece, errors="coerce")
            n = int(runs[columns[0][1]].notna().sum())
            curves.append({
                "label": f"{setting}{' at T = 1' if dashed else ''}"
                         + (f" (mean of {n})" if n > 1 else ""),
                "alphas": [a for a, _ in columns],
                "coverage": [float(runs[c].mean()) for _, c in columns],
                "ece": float(ece.mean()) if ece.notna().any() else None,
                "color": f"C{i % 10}",
                "dashed": dashed,
            })  # fmt: skip
    if not curves:
        return False
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.0, 5.5))
    save_figure(reliability_figure(curves, ax=fig.subplots()), path, dpi=100)
    return True


def draw_beliefs(done: pd.DataFrame, out: Path) -> tuple[dict, list[str]]:
    """The beliefs section of report.md, for runs whose metrics.json has belief or uncertainty
    metrics (issue 17): a table per setting (the median over its runs) of the median error, the
    NLL and ECE (tempered, and at T = 1 where a temperature was fitted), each OOD score's
    Spearman correlation with the error and AUROC at flagging the noisiest decile; and the
    reliability diagram `reliability.png` (one curve per setting, the mean coverage over its runs;
    the untempered belief dashed). ({file key: path}, report.md lines); nothing without such runs.
    """
    keys = [c for c, _ in BELIEF_COLUMNS[1:] + _score_columns(done) if c in done]
    keys += [c for _, c in _coverage_columns(done, "test/")]
    if not keys:
        return {}, []
    rows = [s for s in setting_order(done)
            if done.loc[done["setting"] == s, keys].notna().any().any()]  # fmt: skip
    if not rows:
        return {}, []
    md = ["## Beliefs: likelihood, calibration and uncertainty scores", "",
          "Per setting, the median over its runs. NLL: mean negative log-likelihood of the test "
          "targets in nats, w.r.t. the uniform probability measure on SO(3) (lower is better). "
          "ECE: mean |coverage - alpha| of the highest-density credible regions at alpha = "
          "0.1 ... 0.9 (0: calibrated). T: the fitted belief temperature (A -> A / T); at T = 1: "
          "the belief before it. Spearman: rank correlation of each uncertainty score with the "
          "error (dt: positive is good; eigengap and raw_norm: negative is good). AUROC "
          "noisiest: how well the score flags the noisiest tenth of the test samples (1 "
          "perfect, 0.5 chance).", "", _beliefs_table(done, rows), ""]  # fmt: skip
    files = {}
    if _reliability(done, out / "reliability.png"):
        files["reliability"] = out / "reliability.png"
        md += ["Reliability of the credible regions (coverage against level; on the diagonal: "
               "calibrated, below it: over-confident):", "",
               "![reliability diagram](reliability.png)", ""]  # fmt: skip
    return files, md
