"""Every table rotlearn writes, built by one function, `markdown_table`: the report's tables
(report.md), each OOD run's ood.md, and the one-table summary of a run in TensorBoard's Text tab.

A leaf of floor 4 (pandas and floors 0-1): floor-3 callbacks write their tables with it.
Numbers are rounded for reading (`digits`, or a format per column); NaN and missing values read
"-"; an infinite value reads "inf" and the table then ends with a line that says what it means
(`INFINITE_NOTE`); every cell and header is text as written (`markdown_text`).
"""

from __future__ import annotations

import math
import re
import unicodedata
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd

__all__ = [
    "BELIEF_COLUMNS",
    "LABELS",
    "PAPER_COLUMNS",
    "TABLE_ONE_COLUMNS",
    "beliefs_table",
    "box_table",
    "failed_table",
    "markdown_table",
    "markdown_text",
    "mean_range",
    "ood_markdown",
    "paper_table",
    "percentile_table",
    "results_table",
    "score_table",
    "seeds_table",
    "sets_table",
    "setting_order",
    "table_one_rows",
]

ORACLE = "error"  # the score of the report's oracle row: each pair's own error (its samples')
LABELS = {"dt": "DT", "eigengap": "gap", "raw_norm": "norm", "autoencoder": "AE",
          ORACLE: "own error (oracle)"}  # fmt: skip
INFINITE_NOTE = ("inf: the run recorded an infinite value (it overflowed: a diverged metric), "
                 "not a large number rounded")  # fmt: skip
Format = str | Callable[[Any], str]


def _missing(value: Any) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value)) or value is pd.NA


_MARKDOWN = re.compile(r"([\\\[\]|#])")  # a backslash, links and images, table cells, headings


def markdown_text(value: Any) -> str:
    """`value` as Markdown text that reads as written, whatever a received run's config says:
    line breaks and other control characters become spaces (no new rows, headings or blocks),
    `&`, `<`, `>` HTML entities (no raw HTML: `<script>`, `<img onerror=...>`), and a
    backslash, `[`, `]`, `|` and `#` backslash-escaped (no links such as
    `[x](javascript:...)`, no table cells, no headings)."""
    text = "".join(
        " " if unicodedata.category(c)[0] in "CZ" and c != " " else c for c in str(value)
    )
    text = text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
    return _MARKDOWN.sub(r"\\\1", text)


def _cell(value: Any, fmt: Format | None, digits: int) -> str:
    if _missing(value):
        return "-"
    if fmt is not None:
        text = fmt(value) if callable(fmt) else fmt.format(value)
    elif isinstance(value, (float, np.floating)):
        text = f"{value:.{digits}f}"
    else:
        text = str(value)
    return markdown_text(text)


def markdown_table(
    rows: pd.DataFrame | Sequence[Mapping[str, Any]],
    columns: Sequence[str | tuple[str, str]] | None = None,
    formats: Mapping[str, Format] | None = None,
    digits: int = 2,
) -> str:
    """A GitHub-flavoured markdown table.

    Args:
        rows: a DataFrame, or one mapping per row.
        columns: the keys to show, each a key (its header too) or (key, header); None: every
            key of the rows, in order.
        formats: key -> format string ("{:.3g}") or function, for that column's numbers.
        digits: decimals of the other floats.
    """
    records = rows.to_dict("records") if isinstance(rows, pd.DataFrame) else [dict(r) for r in rows]
    if columns is None:
        columns = list(dict.fromkeys(k for r in records for k in r))
    pairs = [(c, c) if isinstance(c, str) else (c[0], c[1]) for c in columns]
    formats = dict(formats or {})
    headers = [markdown_text(header) for _, header in pairs]
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(pairs)]
    infinite = False
    for record in records:
        values = [record.get(key) for key, _ in pairs]
        infinite |= any(isinstance(v, (float, np.floating)) and np.isinf(v) for v in values)
        cells = [
            _cell(v, formats.get(key), digits) for v, (key, _) in zip(values, pairs, strict=True)
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join([*lines, "", INFINITE_NOTE] if infinite else lines)


def setting_order(done: pd.DataFrame, column: str = "setting") -> list[Any]:
    """The distinct values of `column`, in the order of their first job (the sweep's order)."""
    return list(dict.fromkeys(done[column].dropna())) if column in done else []


# ---------------------------------------------------------------------------- a run, one table

_RESULT_ROWS = [
    ("test/err_mean", "test error, mean (deg)"),
    ("test/err_median", "test error, median (deg)"),
    ("test/err_p10", "test error, p10 (deg)"),
    ("test/err_p90", "test error, p90 (deg)"),
    ("test/identity_err_mean", "predict identity, mean (deg)"),
    ("test/err_vs_identity", "error / identity's"),
    ("test/recon_mean", "reconstruction L1"),
    ("test/nll", "NLL (nats)"),
    ("test/ece", "ECE"),
    ("test/temperature", "temperature T"),
    ("test/uncalibrated_nll", "NLL at T = 1"),
    ("test/uncalibrated_ece", "ECE at T = 1"),
    ("calibration/val_nll", "validation NLL, calibrated (nats)"),
    ("calibration/val_nll_uncalibrated", "validation NLL at T = 1 (nats)"),
]


def results_table(metrics: Mapping[str, Any]) -> str:
    """A run's one-shot results as one two-column table (TensorBoard's Text tab): test errors,
    the identity baseline, the belief's NLL and ECE (and at T = 1), each uncertainty score's
    Spearman correlation with the error and AUROC at flagging the noisiest tenth, each OOD
    score's AUROC, the epochs and which weights were tested."""
    rows = [
        {"result": label, "value": metrics[key]} for key, label in _RESULT_ROWS if key in metrics
    ]
    for key in sorted(metrics):
        if key.startswith("test/") and key.endswith("_spearman"):
            rows.append({"result": f"{key[5:-9]}: Spearman with error", "value": metrics[key]})
        elif key.startswith("test/") and key.endswith("_auroc_noisiest"):
            rows.append({"result": f"{key[5:-15]}: AUROC, noisiest 10 %", "value": metrics[key]})
        elif key.startswith("ood/auroc_"):
            rows.append({"result": f"OOD AUROC, {key[10:]}", "value": metrics[key]})
    for key, label in (
        ("epochs", "epochs"),
        ("tested_weights", "weights tested"),
        ("diverged", "diverged"),
    ):
        if key in metrics:
            rows.append({"result": label, "value": metrics[key]})
    return markdown_table(rows, ["result", "value"], formats={"value": _value_text})


def _value_text(value: Any) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


# ---------------------------------------------------------------------------- the report


def percentile_table(
    done: pd.DataFrame,
    metric: str = "test/err_mean",
    medians: str | None = "test/err_median",
    name: str = "test err mean",
) -> str:
    """Per setting: its runs and the 10th, 50th, 90th percentile of their final `metric` (the
    mean test error; `name` in the header), and the median of their per-run `medians` (None: no
    such column). Where every setting has one run, its `metric` and `medians` alone (three
    percentiles of one number said it three times)."""
    rows = []
    for setting in setting_order(done):
        runs = done[done["setting"] == setting]
        values = runs[metric].to_numpy(dtype=float)
        p10, p50, p90 = np.percentile(values, [10, 50, 90])
        row = {"setting": setting, "runs": len(values), "p10": p10, "p50": p50, "p90": p90}
        if medians is not None:
            row["medians"] = float(np.median(runs[medians].to_numpy(float)))
        rows.append(row)
    if all(row["runs"] == 1 for row in rows):
        own = [("medians", medians.replace("/", " ").replace("_", " "))] if medians else []
        return markdown_table(rows, [("setting", "setting"), ("p50", name), *own], digits=3)
    columns = [
        ("setting", "setting"),
        ("runs", "runs"),
        ("p10", f"{name}: p10"),
        ("p50", "median"),
        ("p90", "p90"),
        *([("medians", "median of per-run medians")] if medians is not None else []),
    ]
    return markdown_table(rows, columns, digits=3)


def box_table(
    done: pd.DataFrame, x: str, label: str, rows: Sequence[Any], values: Sequence[Any]
) -> str:
    """The median test error of each row (a setting without `x`) per value of `x` (columns)."""
    head = [
        (f"v{i}", f"{label} {v:g}" if isinstance(v, (int, float)) else f"{label} {v}")
        for i, v in enumerate(values)
    ]
    records = []
    for row in rows:
        record: dict[str, Any] = {"row": row}
        for i, v in enumerate(values):
            sel = done[(done["series"] == row) & (done[x] == v)]["test/err_median"]
            record[f"v{i}"] = float(sel.median()) if len(sel) else None
        records.append(record)
    return markdown_table(records, [("row", "setting"), *head], digits=3)


BELIEF_COLUMNS = [
    ("test/err_median", "median err (deg)"),
    ("test/nll", "NLL (nats)"),
    ("test/ece", "ECE"),
    ("test/temperature", "T"),
    ("test/uncalibrated_nll", "NLL at T = 1"),
    ("test/uncalibrated_ece", "ECE at T = 1"),
    ("calibration/val_nll", "validation NLL, calibrated (nats)"),
    ("calibration/val_nll_uncalibrated", "validation NLL at T = 1 (nats)"),
]


def score_columns(done: pd.DataFrame, order: Sequence[str] = ()) -> list[tuple[str, str]]:
    """(column, header) of every test/<score>_spearman, then test/<score>_auroc_noisiest, the
    scores in `order` first (others after, by name)."""
    rank = {name: i for i, name in enumerate(order)}
    columns = []
    for suffix, what in (("_spearman", "Spearman"), ("_auroc_noisiest", "AUROC noisiest")):
        names = [
            str(c) for c in done.columns if str(c).startswith("test/") and str(c).endswith(suffix)
        ]
        scores = sorted((n[5 : -len(suffix)] for n in names), key=lambda s: (rank.get(s, 99), s))
        columns += [(f"test/{score}{suffix}", f"{score} {what}") for score in scores]
    return columns


def beliefs_table(done: pd.DataFrame, rows: Sequence[Any], order: Sequence[str] = ()) -> str:
    """Per setting: the median over its runs of each belief metric any run has."""
    columns = [
        (c, h)
        for c, h in BELIEF_COLUMNS + score_columns(done, order)
        if c in done and done[c].notna().any()
    ]
    records = []
    for setting in rows:
        runs = done[done["setting"] == setting]
        record = {"setting": setting, "runs": len(runs)}
        for column, _ in columns:
            values = pd.to_numeric(runs[column], errors="coerce").dropna()
            record[column] = float(values.median()) if len(values) else None
        records.append(record)
    return markdown_table(
        records,
        [("setting", "setting"), ("runs", "runs"), *columns],
        formats={"test/temperature": "{:.3g}"},
        digits=3,
    )


def failed_table(failed: pd.DataFrame) -> str:
    """The jobs that failed, were interrupted or never ran."""
    return markdown_table(failed, ["job", "status", "overrides", "error"])


# ---------------------------------------------------------------------------- OOD (Table I)

TABLE_ONE_COLUMNS = [
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


def table_one_rows(rep: str, frame: pd.DataFrame) -> list[dict[str, Any]]:
    """Table I rows of one run: the head unfiltered, then the head + each score at its table q.

    Args:
        rep: the head's name (or the run's label).
        frame: the OOD evaluation's rows (columns of `rotlearn.ood.evaluation.rejection_row`
            plus set and in_table); the unfiltered row takes their err_mean_all.
    """
    table = frame[frame["in_table"]]

    def first(sub: pd.DataFrame, key: str) -> float:
        return float(sub[key].iloc[0]) if len(sub) else math.nan

    clean_all = first(frame[frame["set"] == "clean"], "err_mean_all")
    corrupted_all = first(frame[frame["set"] == "corrupted"], "err_mean_all")
    rows = [
        {
            "method": rep,
            "q": "-",
            "clean err (deg)": clean_all,
            "clean kept %": 100.0,
            "corrupted err (deg)": corrupted_all,
            "corrupted kept %": 100.0,
            "precision %": math.nan,
            "recall %": 100.0,
            "AUROC": math.nan,
        }
    ]
    for name in table["score"].unique():
        clean = table[(table["score"] == name) & (table["set"] == "clean")]
        corrupted = table[(table["score"] == name) & (table["set"] == "corrupted")]
        rows.append(
            {
                "method": f"{rep} + {LABELS.get(name, name)}",
                "q": first(clean, "q"),
                "clean err (deg)": first(clean, "err_mean_kept"),
                "clean kept %": first(clean, "kept_pct"),
                "corrupted err (deg)": first(corrupted, "err_mean_kept"),
                "corrupted kept %": first(corrupted, "kept_pct"),
                "precision %": first(corrupted, "precision"),
                "recall %": first(corrupted, "recall"),
                "AUROC": first(corrupted, "auroc"),
            }
        )
    return rows


SEED_COLUMNS = TABLE_ONE_COLUMNS[2:]  # the numbers of a Table I row (method and q are its name)


def seeds_table(rows: pd.DataFrame) -> str:
    """Table I over trials (seeds): per method (a setting's label and its score; runs that
    differ only in their trial keys share it), the number of runs and, for each number, its mean
    and range over them as `mean (min-max)`; a single run shows its number alone.

    Args:
        rows: Table I rows of every run (`table_one_rows`, several runs per method).
    """
    records = []
    for method, group in rows.groupby("method", sort=False):
        record = {"method": method, "runs": len(group), "q": group["q"].iloc[0]}
        record.update({column: mean_range(group[column]) for column in SEED_COLUMNS})
        records.append(record)
    return markdown_table(records, ["method", "runs", "q", *SEED_COLUMNS])


def mean_range(column: pd.Series, brackets: str = "()") -> str | None:
    """A number over runs as `mean (min-max)` (`brackets`: around the range), or alone where
    the runs agree (None: no number)."""
    values = pd.to_numeric(column, errors="coerce").dropna().to_numpy(float)
    if len(values) == 0:
        return None
    if len(values) == 1 or np.ptp(values) == 0:
        return f"{values.mean():.2f}"
    opening, closing = brackets
    return f"{values.mean():.2f} {opening}{values.min():.2f}-{values.max():.2f}{closing}"


REFERENCE_WORDS = {  # how ood.md names the set the thresholds come from
    "val": "validation (held-out training-side pairs)",
    "train": "training (the paper's protocol, section V-A)",
}


def ood_markdown(rep: str, frame: pd.DataFrame) -> str:
    """A run's `ood.md`: Table I (paper) and every score at every quantile."""
    from rotlearn.ood.evaluation import reference_set

    reference = reference_set(frame)
    n = int(frame["n"].iloc[0]) if len(frame) else 0
    corrupted = frame[frame["set"] == "corrupted"]
    n_corrupted = int(corrupted["n_corrupted"].iloc[0]) if len(corrupted) else 0
    detail = [
        "score",
        "keep",
        "q",
        "set",
        "kept_pct",
        "err_mean_kept",
        "err_median_kept",
        "precision",
        "recall",
        "auroc",
        "spearman",
        "nan_scores",
    ]
    intro = (
        f"Test set: {n} pairs; the corrupted set erases the last {n_corrupted} of them (random "
        "erasing, as in the paper's Table I). Errors are mean angles in degrees over the kept "
        "pairs; precision and recall are of keeping clean pairs. Thresholds: quantile q of the "
        f"{REFERENCE_WORDS.get(reference, reference)} scores."
    )
    parts = [
        f"# OOD evaluation ({rep} head)",
        intro,
        "## Table I",
        "Each score at its Table I quantile (`callbacks.ood.table`, e.g. DT at the paper's "
        "q = 0.75, even where other quantiles were asked; a score not listed there: the largest "
        "asked q <= 0.75). Every quantile asked is in the next table.",
        markdown_table(table_one_rows(rep, frame), TABLE_ONE_COLUMNS),
        "## Every score and quantile",
        markdown_table(frame, detail),
    ]
    return "\n\n".join(parts) + "\n"


PAPER_COLUMNS = [
    ("clean err (deg)", "clean_err"),
    ("clean kept %", "clean_kept"),
    ("corrupted err (deg)", "corrupted_err"),
    ("corrupted kept %", "corrupted_kept"),
    ("precision %", "precision"),
]


def paper_table(ood: pd.DataFrame, paper: Mapping[str, Any]) -> str:
    """Our Table I rows beside the paper's: for each paper row ({rep, score (absent: the head
    alone), clean_err, clean_kept, corrupted_err, corrupted_kept, precision}), our first method
    with that head and score among the runs matching `paper.where` ({group: choice}), each
    number as `ours (paper)`, ours over that method's runs (seeds) as `mean [min-max]`; our
    methods without a paper row are listed after, as `ours (-)`."""
    where = {f"group:{k}": str(v) for k, v in (paper.get("where") or {}).items()}
    comparable = ood
    for key, value in where.items():
        if key in comparable:
            comparable = comparable[comparable[key].astype(str) == value]

    def cell(runs: pd.DataFrame | None, column: str, theirs: Any) -> str:
        ours = None if runs is None else mean_range(runs[column], "[]")
        number = isinstance(theirs, (int, float)) and not isinstance(theirs, bool)
        return f"{ours or '-'} ({f'{theirs:g}' if number else '-'})"  # a run's config: any value

    def record(method: str | None, paper_method: str | None, theirs: Mapping[str, Any]) -> dict:
        runs = None if method is None else ood[ood["method"] == method]
        return {
            "method": "(not run)" if method is None else method,
            "runs": 0 if runs is None else len(runs),
            "paper": paper_method,
            "AUROC": None if runs is None else mean_range(runs["AUROC"]),
            **{column: cell(runs, column, theirs.get(key)) for column, key in PAPER_COLUMNS},
        }

    records, used = [], set()
    for entry in paper.get("rows") or []:
        if not isinstance(entry, Mapping):
            continue
        rep, score = str(entry.get("rep")), str(entry.get("score") or "")
        match = comparable[(comparable["rep"] == rep) & (comparable["score"] == score)]
        method = match["method"].iloc[0] if len(match) else None
        used.add(method)
        label = entry.get("label", rep + (f" + {LABELS.get(score, score)}" if score else ""))
        records.append(record(method, label, entry))
    records += [record(m, None, {}) for m in ood["method"].unique() if m not in used]
    columns = [
        ("method", "method"),
        ("runs", "runs"),
        ("paper", "paper method"),
        *[(c, c) for c, _ in PAPER_COLUMNS],
        ("AUROC", "AUROC"),
    ]
    return markdown_table(records, columns)


def score_table(
    frames: Sequence[tuple[pd.Series, pd.DataFrame]],
    quantiles: Sequence[float] | None,
    set_names: Mapping[str, str],
) -> str:
    """Every score of every run on every flagged test set: AUROC, then per quantile q (those of
    `quantiles` the runs evaluated; None: all) the kept %, the mean and median error of the
    kept pairs, precision and the % of OOD pairs rejected."""
    records = []
    for run, frame in frames:
        for (score, test_set), rows in frame.groupby(["score", "set"], sort=False):
            if quantiles is not None:
                rows = rows[rows["q"].apply(lambda q: any(np.isclose(q, quantiles)))]
            for i, (_, row) in enumerate(rows.iterrows()):
                records.append(
                    {
                        "method": f"{run['setting']} + {LABELS.get(score, score)}"
                        if i == 0
                        else "",
                        "set": set_names.get(test_set, test_set) if i == 0 else "",
                        "AUROC": row["auroc"] if i == 0 else "",
                        "q": f"{row['q']:g}",
                        "kept %": row["kept_pct"],
                        "kept err mean": row["err_mean_kept"],
                        "kept err median": row["err_median_kept"],
                        "precision %": row["precision"],
                        "OOD rejected %": row.get("ood_rejected"),
                    }
                )
    columns = [
        "method",
        "set",
        "AUROC",
        "q",
        "kept %",
        "kept err mean",
        "kept err median",
        "precision %",
        "OOD rejected %",
    ]
    return markdown_table(records, columns)


def sets_table(
    frames: Sequence[tuple[pd.Series, pd.DataFrame]], set_names: Mapping[str, str]
) -> str:
    """The error per test set (paper Fig. 8): per run, the head unfiltered and with each score
    at its Table I quantile, the mean error of the kept pairs (and kept %) on the clean test
    set and on each extra set (the clean test set plus unseen pairs)."""
    sets = list(dict.fromkeys(s for _, f in frames for s in f["set"] if s != "corrupted"))
    records = []
    for run, frame in frames:
        table = frame[frame["in_table"]]
        record = {"method": run["setting"]}
        for s in sets:
            rows = frame[frame["set"] == s]
            record[s] = f"{rows['err_mean_all'].iloc[0]:.2f} (100 %)" if len(rows) else None
        records.append(record)
        for score in table["score"].unique():
            record = {"method": f"{run['setting']} + {LABELS.get(score, score)}"}
            for s in sets:
                rows = table[(table["score"] == score) & (table["set"] == s)]
                kept = rows.iloc[0] if len(rows) else None
                record[s] = (
                    None
                    if kept is None
                    else f"{kept['err_mean_kept']:.2f} ({kept['kept_pct']:.0f} %)"
                )
            records.append(record)
    return markdown_table(records, ["method", *[(s, set_names.get(s, s)) for s in sets]])
