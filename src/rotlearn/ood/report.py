"""Writers of the OOD evaluation: Table I-style markdown and CSV, the calibrated-threshold file,
and TensorBoard scalars and figures (precision-recall curve, score-vs-error scatter, score box
plots as in paper Fig. 6c)."""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd
from torch import Tensor

from rotlearn.checkpoint import THRESHOLDS_FILE
from rotlearn.io import write_json_atomic, write_text_atomic
from rotlearn.ood.evaluation import pr_quantiles, rejection_row
from rotlearn.ood.scores import Score

__all__ = [
    "TABLE_COLUMNS",
    "box_figure",
    "log_tensorboard",
    "ood_markdown",
    "pr_figure",
    "scatter_figure",
    "table_rows",
    "write_tables",
    "write_thresholds",
]

LABELS = {"dt": "DT", "eigengap": "gap", "raw_norm": "norm", "autoencoder": "AE"}
TABLE_COLUMNS = [
    "method",
    "q",
    "clean err (deg)",
    "clean kept %",
    "corrupted err (deg)",
    "corrupted kept %",
    "precision %",
    "recall %",
    "AUROC",
]


def _fmt(value: Any, digits: int = 2) -> str:
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.{digits}f}"
    return str(value)


def table_rows(rep: str, frame: pd.DataFrame) -> list[dict]:
    """Table I rows of one run: the head unfiltered, then the head + each score at its table q.

    Args:
        rep: the head's name.
        frame: the callback's rows (columns of `rejection_row` plus set and in_table); the
            unfiltered row takes their err_mean_all.
    """
    table = frame[frame["in_table"]]

    def first(sub: pd.DataFrame, key: str) -> float:
        return float(sub[key].iloc[0]) if len(sub) else math.nan

    clean_all = first(frame[frame["set"] == "clean"], "err_mean_all")
    corrupted_all = first(frame[frame["set"] == "corrupted"], "err_mean_all")
    rows = [{"method": rep, "q": "-", "clean err (deg)": clean_all, "clean kept %": 100.0,
             "corrupted err (deg)": corrupted_all, "corrupted kept %": 100.0,
             "precision %": math.nan, "recall %": 100.0, "AUROC": math.nan}]  # fmt: skip
    for name in table["score"].unique():
        clean = table[(table["score"] == name) & (table["set"] == "clean")]
        corrupted = table[(table["score"] == name) & (table["set"] == "corrupted")]
        rows.append({
            "method": f"{rep} + {LABELS.get(name, name)}",
            "q": first(clean, "q"),
            "clean err (deg)": first(clean, "err_mean_kept"),
            "clean kept %": first(clean, "kept_pct"),
            "corrupted err (deg)": first(corrupted, "err_mean_kept"),
            "corrupted kept %": first(corrupted, "kept_pct"),
            "precision %": first(corrupted, "precision"),
            "recall %": first(corrupted, "recall"),
            "AUROC": first(corrupted, "auroc"),
        })  # fmt: skip
    return rows


def markdown_table(rows: list[dict], columns: list[str]) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        lines.append("| " + " | ".join(_fmt(row.get(c, "")) for c in columns) + " |")
    return "\n".join(lines)


def ood_markdown(rep: str, frame: pd.DataFrame) -> str:
    """`ood.md` of one run: Table I (paper) and every score at every quantile."""
    n = int(frame["n"].iloc[0]) if len(frame) else 0
    n_corrupted = (
        int(frame[frame["set"] == "corrupted"]["n_corrupted"].iloc[0]) if len(frame) else 0
    )
    detail_columns = ["score", "keep", "q", "set", "kept_pct", "err_mean_kept", "err_median_kept",
                      "precision", "recall", "auroc", "spearman", "nan_scores"]  # fmt: skip
    return "\n\n".join([
        f"# OOD evaluation ({rep} head)",
        f"Test set: {n} pairs; the corrupted set erases the last {n_corrupted} of them "
        "(random erasing, as in the paper's Table I). Errors are mean angles in degrees over the "
        "kept pairs; precision and recall are of keeping clean pairs. Thresholds: quantile q of "
        "the training scores (paper section V-A).",
        "## Table I",
        markdown_table(table_rows(rep, frame), TABLE_COLUMNS),
        "## Every score and quantile",
        markdown_table(frame.to_dict("records"), detail_columns),
    ]) + "\n"  # fmt: skip


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=(4.5, 3.5), dpi=100)


def pr_figure(score: Score, curve: list[dict]):
    """Precision vs recall of keeping clean pairs, q from 0.05 to 0.97 (`pr_quantiles`)."""
    fig, ax = _figure()
    ax.plot([r["recall"] for r in curve], [r["precision"] for r in curve], marker=".")
    ax.set(xlabel="recall %", ylabel="precision %", title=f"{score.name}: corrupted test set")
    fig.tight_layout()
    return fig


def scatter_figure(score: Score, sets: dict[str, dict[str, Tensor]]):
    """Score against error on the clean and the corrupted test pairs."""
    fig, ax = _figure()
    corrupted = sets["corrupted"]
    for flag, label in ((False, "clean"), (True, "corrupted")):
        mask = corrupted["corrupted"] == flag
        ax.scatter(corrupted[score.name][mask], corrupted["error"][mask], s=6, label=label)
    ax.set(xlabel=score.name, ylabel="error (deg)", yscale="log")
    ax.legend()
    fig.tight_layout()
    return fig


def box_figure(score: Score, sets: dict[str, dict[str, Tensor]]):
    """Score distributions on training, test, corrupted and pure-noise inputs (paper Fig. 6c)."""
    fig, ax = _figure()
    corrupted = sets["corrupted"]
    groups = {
        "train": sets["train"][score.name],
        "test": sets["clean"][score.name],
        "corrupted": corrupted[score.name][corrupted["corrupted"]],
        "noise": sets["noise"][score.name],
    }
    ax.boxplot([g[g.isfinite()].numpy() for g in groups.values()], showfliers=False)
    ax.set_xticks(range(1, len(groups) + 1), list(groups))
    ax.set(
        ylabel=score.name,
        title=f"{score.name} ({'low' if score.keep_below else 'high'} = confident)",
    )
    fig.tight_layout()
    return fig


def write_tables(run_dir: str | os.PathLike, rep: str, frame: pd.DataFrame) -> Path:
    """`ood.csv` (every row of `frame`) and `ood.md` (`ood_markdown`) in `run_dir`, atomically;
    returns the markdown's path."""
    run_dir = Path(run_dir)
    write_text_atomic(run_dir / "ood.csv", frame.to_csv(index=False))
    return write_text_atomic(run_dir / "ood.md", ood_markdown(rep, frame))


def write_thresholds(checkpoint_dir: str | os.PathLike, ood: Mapping[str, Any]) -> Path:
    """The calibrated threshold {"score", "threshold", "q"} beside the checkpoints it belongs to
    (`rotlearn.checkpoint.THRESHOLDS_FILE`, read by `rotlearn.load`), atomically."""
    data = {"score": str(ood["score"]), "threshold": float(ood["threshold"]), "q": float(ood["q"])}
    return write_json_atomic(Path(checkpoint_dir) / THRESHOLDS_FILE, data)


def log_tensorboard(
    writer: Any,
    scores: Sequence[Score],
    sets: Mapping[str, Mapping[str, Tensor]],
    frame: pd.DataFrame,
    step: int,
) -> None:
    """Every finite statistic of `frame` as a scalar `ood/<score>/q<q>/<set>/<key>`, and per
    score the precision-recall curve on the corrupted set, the score-vs-error scatter and the
    box plots (`sets` as `rotlearn.ood.evaluation.score_sets` returns them)."""
    for row in frame.itertuples():
        prefix = f"ood/{row.score}/q{row.q:g}/{row.set}"
        for key in ("kept_pct", "err_mean_kept", "precision", "recall", "auroc", "spearman"):
            value = getattr(row, key)
            if not (isinstance(value, float) and math.isnan(value)):
                writer.add_scalar(f"{prefix}/{key}", value, step)
    corrupted = sets["corrupted"]
    for score in scores:
        curve = [
            rejection_row(score, q, sets["train"][score.name], corrupted[score.name],
                          corrupted["error"], corrupted["corrupted"])
            for q in pr_quantiles()
        ]  # fmt: skip
        writer.add_figure(f"ood/{score.name}/precision_recall", pr_figure(score, curve), step)
        writer.add_figure(f"ood/{score.name}/score_vs_error", scatter_figure(score, sets), step)
        writer.add_figure(f"ood/{score.name}/boxes", box_figure(score, sets), step)
    writer.flush()
