"""Writers of the OOD evaluation: Table I-style markdown and CSV, every sample's error and scores
(`ood_samples.csv`, read back by `read_samples`), the calibrated-threshold file, and TensorBoard
scalars and figures (precision-recall curve over q, score-vs-error scatter, score box plots as in
paper Fig. 6c, a grid of erased example pairs with their scores). The figures are also drawn by
`rotlearn-report` from the files a run leaves."""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch
from torch import Tensor

from rotlearn.checkpoint import THRESHOLDS_FILE
from rotlearn.io import read_table, write_json_atomic, write_text_atomic
from rotlearn.ood.evaluation import precision_recall_curve
from rotlearn.ood.scores import Score

__all__ = [
    "SAMPLES_FILE",
    "TABLE_COLUMNS",
    "box_figure",
    "examples_figure",
    "log_tensorboard",
    "ood_markdown",
    "pr_figure",
    "read_samples",
    "save_figure",
    "scatter_figure",
    "table_rows",
    "write_samples",
    "write_tables",
    "write_thresholds",
]

SAMPLES_FILE = "ood_samples.csv"

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


def pr_figure(score: Score, curves: list[dict] | Mapping[str, list[dict]], ax=None, title=None):
    """Precision vs recall of keeping clean pairs, one line per curve (`precision_recall_curve`,
    q from 0.05 to 0.97), the q = 0.25 and 0.75 points marked. `curves`: one curve, or
    {label: curve}. Draws into `ax` when given; returns the figure."""
    fig, ax = _figure() if ax is None else (ax.figure, ax)
    curves = curves if isinstance(curves, Mapping) else {score.name: curves}
    for i, (label, curve) in enumerate(curves.items()):
        ax.plot([r["recall"] for r in curve], [r["precision"] for r in curve], marker=".",
                markersize=3, color=f"C{i}", label=label)  # fmt: skip
        for r in curve:
            if any(math.isclose(r["q"], q) for q in (0.25, 0.75)):
                ax.annotate(f"q={r['q']:g}", (r["recall"], r["precision"]), fontsize=7,
                            color=f"C{i}")  # fmt: skip
    ax.set(xlabel="recall % (clean pairs kept)", ylabel="precision % (kept pairs clean)",
           title=title or f"{score.name}: corrupted test set")  # fmt: skip
    if len(curves) > 1:
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def scatter_figure(score: Score, sets: Mapping[str, Mapping[str, Tensor]], ax=None, title=None):
    """Score against error on the corrupted test set, clean and OOD pairs apart."""
    fig, ax = _figure() if ax is None else (ax.figure, ax)
    corrupted = sets["corrupted"]
    for flag, label in ((False, "clean"), (True, "OOD (erased)")):
        mask = corrupted["corrupted"] == flag
        ax.scatter(corrupted[score.name][mask], corrupted["error"][mask], s=5, alpha=0.6,
                   label=label)  # fmt: skip
    ax.set(xlabel=f"{score.name} ({'low' if score.keep_below else 'high'} = confident)",
           ylabel="error (deg)", yscale="log", title=title)  # fmt: skip
    ax.title.set_fontsize(9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def box_groups(score: Score, sets: Mapping[str, Mapping[str, Tensor]]) -> dict[str, Tensor]:
    """The score's values on training, test, erased, pure-noise and each extra set's OOD pairs
    (those present), finite only: the groups of the box plots (paper Fig. 6c)."""
    groups = {}
    if "train" in sets:
        groups["train"] = sets["train"][score.name]
    if "clean" in sets:
        groups["test"] = sets["clean"][score.name]
    for name, data in sets.items():
        if name in ("train", "clean", "noise") or "corrupted" not in data:
            continue
        groups["erased" if name == "corrupted" else name] = data[score.name][data["corrupted"]]
    if "noise" in sets:
        groups["noise"] = sets["noise"][score.name]
    return {k: v[torch.isfinite(v)] for k, v in groups.items()}


def box_figure(score: Score, sets: Mapping[str, Mapping[str, Tensor]], ax=None, title=None):
    """Score distributions on training, test, erased, extra-set and pure-noise inputs (paper
    Fig. 6c; `box_groups`)."""
    fig, ax = _figure() if ax is None else (ax.figure, ax)
    groups = {k: v for k, v in box_groups(score, sets).items() if len(v)}
    ax.boxplot([g.numpy() for g in groups.values()], showfliers=False)
    ax.set_xticks(range(1, len(groups) + 1), list(groups), fontsize=7)
    ax.set(
        ylabel=score.name,
        title=title or f"{score.name} ({'low' if score.keep_below else 'high'} = confident)",
    )
    ax.title.set_fontsize(9)
    fig.tight_layout()
    return fig


def examples_figure(images: Tensor, captions: Sequence[Mapping[str, Any]]):
    """A grid of test pairs with their error and scores: one row per pair, its two frames side
    by side, the caption above.

    Args:
        images: (K, 2C, S, S) uint8 pairs as the network saw them before normalisation (erased
            where they are), C = 1 or 3.
        captions: per pair {"erased": bool, "error": degrees, <score name>: value, ...}.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    k, channels = images.shape[0], images.shape[1] // 2
    fig, axes = plt.subplots(k, 2, figsize=(4.2, 2.2 * k), dpi=100, squeeze=False)
    for row, (pair, caption) in enumerate(zip(images, captions, strict=True)):
        for col in range(2):
            frame = pair[col * channels : (col + 1) * channels].permute(1, 2, 0).cpu().numpy()
            ax = axes[row][col]
            ax.imshow(frame[..., 0] if channels == 1 else frame, cmap="gray", vmin=0, vmax=255)
            ax.set_xticks([])
            ax.set_yticks([])
        scores = ", ".join(f"{LABELS.get(k, k)} {v:.3g}" for k, v in caption.items()
                           if k not in ("erased", "error"))  # fmt: skip
        kind = "erased" if caption.get("erased") else "clean"
        axes[row][0].set_title(f"{kind}, err {caption['error']:.2f} deg: {scores}", fontsize=7,
                               loc="left")  # fmt: skip
    fig.tight_layout()
    return fig


def save_figure(fig: Any, path: str | os.PathLike, dpi: int = 100) -> Path:
    """Save a matplotlib figure as PNG to a temporary file beside `path`, then rename it over
    `path` (never half-written)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        fig.savefig(tmp, dpi=dpi, format="png")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_samples(run_dir: str | os.PathLike, sets: Mapping[str, Mapping[str, Tensor]]) -> Path:
    """`ood_samples.csv` in `run_dir`: one row per scored sample, columns set, error (degrees),
    ood (1/0, empty for the unflagged train and noise sets) and one per score; atomically."""
    frames = []
    for name, data in sets.items():
        columns = {"set": name, "error": data["error"].numpy()}
        if "corrupted" in data:
            columns["ood"] = data["corrupted"].numpy().astype(int)
        for key, values in data.items():
            if key not in ("error", "corrupted"):
                columns[key] = values.numpy()
        frames.append(pd.DataFrame(columns))
    frame = pd.concat(frames, ignore_index=True)
    return write_text_atomic(Path(run_dir) / SAMPLES_FILE, frame.to_csv(index=False))


def read_samples(path: str | os.PathLike) -> dict[str, dict[str, Tensor]]:
    """The sets of `write_samples`' file, as `rotlearn.ood.evaluation.score_sets` returns them
    (float64 tensors, bool "corrupted" where flagged).

    Raises:
        ValueError: naming the file, if it lacks the set or error column.
    """
    frame = read_table(path)
    if not {"set", "error"} <= set(frame.columns):
        raise ValueError(f"{path}: not an OOD samples file (needs the columns set and error)")
    sets = {}
    for name, part in frame.groupby("set", sort=False):
        data = {"error": torch.tensor(part["error"].to_numpy(dtype=np.float64))}
        if "ood" in part and part["ood"].notna().all():
            data["corrupted"] = torch.tensor(part["ood"].to_numpy(dtype=np.int64) != 0)
        for key in part.columns:
            if key not in ("set", "error", "ood"):
                data[key] = torch.tensor(part[key].to_numpy(dtype=np.float64))
        sets[str(name)] = data
    return sets


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
    examples: Any = None,
) -> None:
    """Every finite statistic of `frame` as a scalar `ood/<score>/q<q>/<set>/<key>`, per score
    the precision-recall curve over q on each flagged test set but the clean one, the
    score-vs-error scatter and the box plots (`sets` as `rotlearn.ood.evaluation.score_sets`
    returns them), and the `examples` figure (`examples_figure`) as `ood/examples`."""
    keys = ("kept_pct", "err_mean_kept", "err_median_kept", "precision", "recall", "ood_rejected",
            "auroc", "spearman")  # fmt: skip
    for row in frame.to_dict("records"):
        prefix = f"ood/{row['score']}/q{row['q']:g}/{row['set']}"
        for key in keys:
            value = row.get(key)
            if isinstance(value, (int, float)) and not math.isnan(value):
                writer.add_scalar(f"{prefix}/{key}", value, step)
    flagged = [n for n, v in sets.items() if n != "clean" and "corrupted" in v]
    for score in scores:
        curves = {name: precision_recall_curve(score, sets["train"][score.name], sets[name])
                  for name in flagged}  # fmt: skip
        title = f"{score.name}: precision-recall over q"
        writer.add_figure(f"ood/{score.name}/precision_recall", pr_figure(score, curves,
                          title=title), step)  # fmt: skip
        writer.add_figure(f"ood/{score.name}/score_vs_error", scatter_figure(score, sets), step)
        writer.add_figure(f"ood/{score.name}/boxes", box_figure(score, sets), step)
    if examples is not None:
        writer.add_figure("ood/examples", examples, step, close=False)
    writer.flush()
