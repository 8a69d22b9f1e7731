"""`rotlearn-report <sweep dir>`: tables and plots of a sweep, made from its run directories alone.

Writes into the sweep directory (or --out): `summary.csv` (one row per job, failed, interrupted and
never-run ones too), `report.md` (per-representation percentiles of the final test error over
trials, a table per phi_max when it was swept, the jobs that failed, were interrupted or never
ran: those listed PENDING in the sweep's jobs.json), `curves.png` (paper Fig. 3: per-epoch median
over trials with a 10-90 % band, train and validation) and `phi_max_box.png` (paper Fig. 4: box
plots of log10 per-sample test error per phi_max) when the sweep has what they need.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from rotlearn.io import write_text_atomic
from rotlearn.ood.report import TABLE_COLUMNS, markdown_table, table_rows

__all__ = ["collect_runs", "main", "make_report"]

log = logging.getLogger("rotlearn")
REPS = ["quat", "sixd", "a", "svd9d"]  # the order tables and plots use


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _run_dirs(root: Path) -> list[Path]:
    if (root / ".hydra" / "config.yaml").is_file():
        return [root]
    return sorted(
        (p.parent.parent for p in root.glob("*/.hydra/config.yaml")),
        key=lambda p: (not p.name.isdigit(), int(p.name) if p.name.isdigit() else 0, p.name),
    )


def collect_runs(root: str | Path) -> pd.DataFrame:
    """One row per run directory below `root`: its config values, status and final metrics."""
    rows = []
    for run in _run_dirs(Path(root)):
        cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
        metrics = _read_json(run / "metrics.json") or {}
        status = _read_json(run / "status.json") or {}
        state = status.get("status") or ("COMPLETED" if metrics else "INCOMPLETE")
        row = {
            "job": run.name,
            "dir": str(run),
            "status": state,
            "error": status.get("error"),  # INTERRUPTED: the signal, the epoch, the resume command
            "overrides": " ".join(OmegaConf.load(run / ".hydra" / "overrides.yaml"))
            if (run / ".hydra" / "overrides.yaml").is_file()
            else "",
            "rep": OmegaConf.select(cfg, "rep.name"),
            "phi_max_deg": OmegaConf.select(cfg, "data.phi_max_deg", default=None),
            "trial": OmegaConf.select(cfg, "trial", default=None),
            "seed": OmegaConf.select(cfg, "seed", default=None),
        }
        try:
            row["lr"] = float(OmegaConf.select(cfg, "optim.lr"))
        except Exception:  # an unresolvable interpolation in a damaged config
            row["lr"] = np.nan
        row.update({k: v for k, v in metrics.items() if isinstance(v, (int, float))})
        rows.append(row)
    return pd.DataFrame(rows + _unstarted_jobs(Path(root), {row["job"] for row in rows}))


def _unstarted_jobs(root: Path, seen: set[str]) -> list[dict[str, Any]]:
    """Rows for the jobs that `<root>/jobs.json` lists but that have no run directory (yet): those
    that never ran (PENDING), or died before Hydra wrote their config."""
    summary = _read_json(root / "jobs.json") or {}
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


def _curves(run: Path, tag: str) -> np.ndarray | None:
    """Per-epoch values of a scalar, from the run's CSV log or else its TensorBoard events."""
    csv = run / "csv" / "metrics.csv"
    if csv.is_file():
        frame = pd.read_csv(csv)
        if tag in frame:
            values = frame.dropna(subset=[tag]).groupby("epoch")[tag].last()
            return values.to_numpy(dtype=float)
    events = run / "tensorboard"
    if events.is_dir():
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

        acc = EventAccumulator(str(events), size_guidance={"scalars": 0}).Reload()
        if tag in acc.Tags().get("scalars", []):
            return np.array([e.value for e in acc.Scalars(tag)], dtype=float)
    return None


def _ordered(reps) -> list[str]:
    present = [r for r in REPS if r in set(reps)]
    return present + sorted(set(reps) - set(present))


# Swept keys that are trials of one setting (pooled in the tables), not settings of their own.
TRIAL_KEYS = {"rep", "trial", "seed", "data.seed", "optim.lr", "data.phi_max_deg"}


def _groups(runs: pd.DataFrame) -> pd.Series:
    """Each run's setting: its rep plus every other swept key (e.g. `a loss=bingham`), so that a
    sweep over a key besides rep, lr, trial and phi_max is never pooled in the tables."""
    overrides = [
        dict(o.lstrip("+~").split("=", 1) for o in str(text).split() if "=" in o)
        for text in runs["overrides"]
    ]
    keys = sorted({k for o in overrides for k in o} - TRIAL_KEYS)
    swept = [k for k in keys if len({o.get(k) for o in overrides}) > 1]
    return pd.Series(
        [
            " ".join([str(rep), *(f"{k}={o.get(k, '-')}" for k in swept)])
            for rep, o in zip(runs["rep"], overrides, strict=True)
        ],
        index=runs.index,
    )


def _percentile_table(done: pd.DataFrame) -> str:
    lines = [
        "| setting | trials | test err mean: p10 | median | p90 | median of per-run medians |",
        "|---|---|---|---|---|---|",
    ]
    groups = _groups(done)
    order = {rep: i for i, rep in enumerate(_ordered(done["rep"]))}
    for group in sorted(groups.unique(), key=lambda g: (order.get(g.split()[0], 99), g)):
        errs = done.loc[groups == group, "test/err_mean"].to_numpy(dtype=float)
        meds = done.loc[groups == group, "test/err_median"].to_numpy(dtype=float)
        p10, p50, p90 = np.percentile(errs, [10, 50, 90])
        lines.append(
            f"| {group} | {len(errs)} | {p10:.3f} | {p50:.3f} | {p90:.3f} | {np.median(meds):.3f} |"
        )
    return "\n".join(lines)


def _phi_max_table(done: pd.DataFrame) -> str:
    angles = sorted(done["phi_max_deg"].dropna().unique())
    head = "| rep | " + " | ".join(f"phi_max {a:g}" for a in angles) + " |"
    lines = [head, "|---|" + "---|" * len(angles)]
    for rep in _ordered(done["rep"]):
        cells = []
        for a in angles:
            sel = done[(done["rep"] == rep) & (done["phi_max_deg"] == a)]["test/err_median"]
            cells.append(f"{sel.median():.3f}" if len(sel) else "-")
        lines.append(f"| {rep} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _plot_curves(done: pd.DataFrame, path: Path) -> bool:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [("train/err_mean", "train"), ("val/err_mean", "validation")]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    drew = False
    for ax, (tag, title) in zip(axes, panels, strict=True):
        for rep in _ordered(done["rep"]):
            curves = [_curves(Path(d), tag) for d in done.loc[done["rep"] == rep, "dir"]]
            curves = [c for c in curves if c is not None and len(c)]
            if not curves:
                continue
            n = min(len(c) for c in curves)
            stack = np.stack([c[:n] for c in curves])
            p10, p50, p90 = np.percentile(stack, [10, 50, 90], axis=0)
            epochs = np.arange(1, n + 1)
            ax.plot(epochs, p50, label=f"{rep} (median of {len(curves)})")
            ax.fill_between(epochs, p10, p90, alpha=0.25)
            drew = True
        ax.set(title=f"{title} mean error", xlabel="epoch", yscale="log")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("mean angular error (deg)")
    axes[1].legend()
    fig.tight_layout()
    if drew:
        fig.savefig(path, dpi=110)
    plt.close(fig)
    return drew


def _plot_phi_max(done: pd.DataFrame, path: Path) -> bool:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    angles = sorted(done["phi_max_deg"].dropna().unique())
    reps = _ordered(done["rep"])
    fig, ax = plt.subplots(figsize=(3 + 2 * len(angles), 4))
    width = 0.8 / max(len(reps), 1)
    drew = False
    for i, rep in enumerate(reps):
        data, positions = [], []
        for j, angle in enumerate(angles):
            errors = []
            for d in done[(done["rep"] == rep) & (done["phi_max_deg"] == angle)]["dir"]:
                errors.extend(_read_json(Path(d) / "test_errors.json") or [])
            if errors:
                data.append(np.log10(np.maximum(errors, 1e-6)))
                positions.append(j + (i - (len(reps) - 1) / 2) * width)
        if data:
            box = ax.boxplot(data, positions=positions, widths=width * 0.9, notch=True,
                             patch_artist=True, showfliers=False)  # fmt: skip
            for patch in box["boxes"]:
                patch.set_facecolor(f"C{i}")
            ax.plot([], [], color=f"C{i}", label=rep, linewidth=8)
            drew = True
    ax.set_xticks(range(len(angles)), [f"{a:g}" for a in angles])
    ax.set(xlabel="phi_max (deg)", ylabel="log10 test error (deg)")
    ax.legend()
    ax.grid(True, axis="y", alpha=0.3)
    fig.tight_layout()
    if drew:
        fig.savefig(path, dpi=110)
    plt.close(fig)
    return drew


def _ood_table(done: pd.DataFrame) -> pd.DataFrame | None:
    """Table I rows of every completed run that has an `ood.csv` (OOD evaluation)."""
    rows = []
    for _, run in done.iterrows():
        path = Path(run["dir"]) / "ood.csv"
        if path.is_file():
            frame = pd.read_csv(path)
            rows += [{"job": run["job"], **row} for row in table_rows(run["rep"], frame)]
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
    if not done.empty:
        md += ["## Final test error (degrees), over trials", "", _percentile_table(done), ""]
        if done["phi_max_deg"].nunique() > 1:
            md += ["## Median test error (degrees) per phi_max", "", _phi_max_table(done), ""]
            if _plot_phi_max(done, out / "phi_max_box.png"):
                files["phi_max_box"] = out / "phi_max_box.png"
                md += ["![log10 test error per phi_max](phi_max_box.png)", ""]
        if _plot_curves(done, out / "curves.png"):
            files["curves"] = out / "curves.png"
            md += ["## Error per epoch", "", "![per-epoch error](curves.png)", ""]
    ood = _ood_table(done)
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
