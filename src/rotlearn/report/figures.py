"""Every figure rotlearn draws, in one place: the report's plots (paper Figs. 3, 4, 6c, 8b), the
reliability diagram, the OOD figures; drawn into PNG files by `rotlearn-report` and into
TensorBoard by the training callbacks.

Each function takes plain data (arrays, numbers, labels) and returns a matplotlib `Figure` built
without pyplot (no global state; safe in any thread), or draws into a given axes. `save_figure`
writes one atomically with the mode the umask allows (`rotlearn.io.atomic_write`). A leaf of
floor 4: it imports numpy, matplotlib and floors 0-1 only, so floor-3 callbacks draw with it.

Axes a person reads: integer epochs, plain numbers on log axes (0.1, 1, 10, not 10^-1), tick
labels and titles that never overlap (rotated or wrapped), legends beside or below the data.
"""

from __future__ import annotations

import math
import os
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rotlearn.bingham.calibration import CREDIBLE_LEVELS
from rotlearn.io import atomic_write
from rotlearn.report.identity import shortened

__all__ = [
    "MAX_TEXT",
    "UNCALIBRATED_ECE",
    "box_groups",
    "calibration_remedy",
    "curves_figure",
    "error_boxes_figure",
    "examples_figure",
    "grid",
    "new_figure",
    "pr_figure",
    "reliability_figure",
    "save_figure",
    "scatter_figure",
    "score_boxes_figure",
    "sets_bars_figure",
]

UNCALIBRATED_ECE = 0.1  # above this ECE the reliability diagram says what to do
MAX_TEXT = 2000  # characters of one text of a figure (a label, a title, the remedies' box)
MAX_POINTS = 5000  # epochs drawn of one curve (a received log of millions overflowed Agg)
LABELS = {"dt": "DT", "eigengap": "gap", "raw_norm": "norm", "autoencoder": "AE"}


def new_figure(width: float, height: float, dpi: int = 100) -> Any:
    """An empty matplotlib Figure of `width` x `height` inches (no pyplot), laid out by
    matplotlib's constrained layout (labels, titles and legends kept inside and apart)."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=dpi, layout="constrained")


def grid(rows: int, cols: int, size: tuple[float, float] = (4.0, 3.2)) -> tuple[Any, Any]:
    """(figure, (rows, cols) axes) of panels of `size` inches, every panel hidden until drawn
    into (`ax.set_visible(True)`)."""
    fig = new_figure(size[0] * cols, size[1] * rows)
    axes = np.atleast_2d(fig.subplots(rows, cols, squeeze=False))
    for ax in axes.flat:
        ax.set_visible(False)
    return fig, axes


def save_figure(fig: Any, path: str | os.PathLike, dpi: int = 100) -> Path:
    """Lay out and save `fig` as a PNG at `path`, atomically (`rotlearn.io.atomic_write`)."""
    _fit(fig)
    with atomic_write(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    return Path(path)


def _fit(fig: Any) -> None:
    """Lay the figure out so that labels, titles and legends stay inside it and apart, and draw
    every text as written: a `$` in a label (a config value of a received run, as
    `data.camera="$\\sqrt{...}$"`) is a dollar sign, not TeX math that matplotlib parses (a
    RecursionError or ParseFatalException midway through a report), at most `MAX_TEXT`
    characters (a received value of 100000 took 50 s to draw in a legend)."""
    if fig.get_layout_engine() is None:
        fig.set_layout_engine("constrained")
    for text in fig.findobj(lambda artist: hasattr(artist, "set_parse_math")):
        text.set_parse_math(False)
        text.set_text(shortened(text.get_text(), MAX_TEXT))


def _wrap(text: str, width: int = 40) -> str:
    return "\n".join(textwrap.wrap(text, width)) or text


def _plain_numbers(axis: Any) -> None:
    """Tick labels of a (log) axis as plain numbers: 0.1, 1, 10, 60 (not 10^-1 or 6x10^1)."""
    from matplotlib.ticker import FuncFormatter, LogLocator

    def plain(value: float, _: Any) -> str:
        return f"{value:g}" if value > 0 else ""

    axis.set_major_formatter(FuncFormatter(plain))
    low, high = axis.get_view_interval()
    if low > 0 and high / low < 100:  # under two decades: label 2x and 5x too
        axis.set_minor_locator(LogLocator(subs=(2.0, 5.0)))
        axis.set_minor_formatter(FuncFormatter(plain))
    else:
        axis.set_minor_formatter(FuncFormatter(lambda *_: ""))


def _integer_ticks(axis: Any) -> None:
    from matplotlib.ticker import MaxNLocator

    axis.set_major_locator(MaxNLocator(integer=True))


# ---------------------------------------------------------------------------------- training


def curves_figure(panels: Mapping[str, Mapping[str, Sequence[np.ndarray]]]) -> Any | None:
    """Per-epoch curves (paper Fig. 3): one panel per metric, one line per label, the median over
    that label's runs with a 10-90 % band where there are several.

    Args:
        panels: metric (panel title) -> label (a group of runs) -> each run's values, the value
            at index i measured after epoch i + 1.

    Returns:
        The Figure (x: epochs trained, integers; y: degrees on a log axis with plain numbers;
        the legend below, "(median of n)" after a label of n > 1 runs), or None when no panel
        has data. A curve of more than `MAX_POINTS` epochs is drawn at `MAX_POINTS` of them,
        evenly spread, the first and last included.
    """
    panels = {
        m: {k: [np.asarray(c, float) for c in v if len(c)] for k, v in p.items()}
        for m, p in panels.items()
    }
    if not any(any(runs for runs in p.values()) for p in panels.values()):
        return None
    labels = list(dict.fromkeys(k for p in panels.values() for k, runs in p.items() if runs))
    fig = new_figure(1.0 + 4.6 * len(panels), 3.6 + 0.25 * math.ceil(len(labels) / 2))
    axes = fig.subplots(1, len(panels), sharey=True, squeeze=False)[0]
    handles = {}
    for ax, (metric, groups) in zip(axes, panels.items(), strict=True):
        for i, label in enumerate(labels):
            runs = groups.get(label) or []
            if not runs:
                continue
            n = min(len(c) for c in runs)
            drawn = np.unique(np.linspace(0, n - 1, min(n, MAX_POINTS)).round().astype(int))
            stack = np.stack([c[drawn] for c in runs])
            p10, p50, p90 = np.percentile(stack, [10, 50, 90], axis=0)
            epochs = drawn + 1
            (line,) = ax.plot(epochs, p50, color=f"C{i % 10}", marker="." if n < 15 else None)
            if len(runs) > 1:
                ax.fill_between(epochs, p10, p90, color=f"C{i % 10}", alpha=0.2, linewidth=0)
            handles[label] = (line, len(runs))
        ax.set(title=metric, xlabel="epochs trained", yscale="log")
        ax.grid(True, which="both", alpha=0.3)
        _integer_ticks(ax.xaxis)
    axes[0].set_ylabel("error (deg, log scale)")
    for ax in axes:
        _plain_numbers(ax.yaxis)
    legend = [
        (h, f"{label} (median of {n})" if n > 1 else label) for label, (h, n) in handles.items()
    ]
    fig.legend(
        [h for h, _ in legend],
        [t for _, t in legend],
        loc="outside lower center",
        ncols=min(2, len(legend)),
        fontsize=8,
        frameon=False,
    )
    _fit(fig)
    return fig


def error_boxes_figure(groups: Mapping[str, Mapping[Any, np.ndarray]], x_label: str) -> Any | None:
    """Box plots of the log10 per-sample test error (paper Fig. 4): for each x value a box per
    label, side by side.

    Args:
        groups: label -> x value -> (n,) errors in degrees (pooled over the label's runs).
        x_label: what the x values are (e.g. "phi_max").
    """
    values = _sorted(v for boxes in groups.values() for v in boxes)
    labels = [label for label, boxes in groups.items() if any(len(e) for e in boxes.values())]
    if not labels or not values:
        return None
    fig = new_figure(3.0 + 1.8 * len(values), 4.2)
    ax = fig.subplots()
    width = 0.8 / len(labels)
    for i, label in enumerate(labels):
        data, positions = [], []
        for j, value in enumerate(values):
            errors = np.asarray(groups[label].get(value, []), float)
            if len(errors):
                data.append(np.log10(np.maximum(errors, 1e-6)))
                positions.append(j + (i - (len(labels) - 1) / 2) * width)
        box = ax.boxplot(
            data,
            positions=positions,
            widths=width * 0.9,
            notch=True,
            patch_artist=True,
            showfliers=False,
        )
        for patch in box["boxes"]:
            patch.set_facecolor(f"C{i % 10}")
        ax.plot([], [], color=f"C{i % 10}", label=label, linewidth=8)
    ax.set_xticks(range(len(values)), [short_number(v) for v in values])
    ax.set(xlabel=x_label, ylabel="log10 test error (deg)")
    ax.grid(True, axis="y", alpha=0.3)
    fig.legend(loc="outside lower center", ncols=min(3, len(labels)), fontsize=8, frameon=False)
    _fit(fig)
    return fig


def short_number(value: Any) -> str:
    return f"{value:g}" if isinstance(value, (int, float)) else str(value)


def _sorted(values: Any) -> list[Any]:
    values = list(dict.fromkeys(values))
    try:
        return sorted(values)
    except TypeError:
        return sorted(values, key=str)


# ---------------------------------------------------------------------------------- beliefs


def calibration_remedy(
    ece: float | None, tempered: bool, likelihood: bool, rep: str | None = None
) -> str | None:
    """What to do about a belief whose ECE exceeds `UNCALIBRATED_ECE` (None: nothing to do).

    Args:
        ece: the belief's expected calibration error.
        tempered: the belief was calibrated already (`calibrate`: a temperature, a level map).
        likelihood: the head was trained with its likelihood (loss=bingham, loss=fisher_nll).
        rep: the head (rep=fisher trains with loss=fisher_nll).
    """
    if ece is None or not math.isfinite(ece) or ece <= UNCALIBRATED_ECE:
        return None
    loss = "loss=fisher_nll" if rep == "fisher" else "loss=bingham"
    steps = []
    if not tempered:
        steps.append("calibrate=true (fits a temperature and a level map on validation)")
    if not likelihood:
        steps.append(f"{loss} (trains the belief)")
    if not steps:
        steps.append("more epochs, or a validation set like the test set")
    state = "still miscalibrated after calibration" if tempered else "uncalibrated"
    return f"{state} (ECE {ece:.2f} > {UNCALIBRATED_ECE:g}); try " + " or ".join(steps)


def _reliability_title(curves: Sequence[Mapping[str, Any]]) -> str:
    eces = [c["ece"] for c in curves if c.get("ece") is not None]
    if len(eces) == 1:
        return f"reliability: ECE {eces[0]:.3f}"
    return "reliability of the credible regions"


def reliability_figure(
    curves: Sequence[Mapping[str, Any]],
    ax: Any = None,
    title: str | None = None,
    remedy: str | None = None,
) -> Any:
    """Coverage of the highest-density credible regions against their level alpha, one line per
    curve, the diagonal coverage = alpha of a calibrated belief dotted in grey: below it the
    belief is over-confident (too sharp), above it too wide.

    Args:
        curves: each {"label": str, "coverage": [fraction per alpha], "alphas": the levels
            (default `CREDIBLE_LEVELS`), "ece": float (optional; in the legend, and in the
            title for one curve), "color" (optional), "dashed": bool (optional)}.
        ax: draw into this axes (its figure is returned); None: a new 5 x 5 inch figure.
        title: None: "reliability: ECE <e>" for one curve, else a plain title.
        remedy: a note drawn under the axes, what to do (`calibration_remedy`).

    Returns:
        The matplotlib Figure. The axes run a little past [0, 1], so a curve on 0 or 1 (a
        belief far too wide or too sharp) stays visible.
    """
    own = ax is None
    if own:
        fig = new_figure(5.0, 5.5 + 0.15 * len(curves))  # a square plot above its legend
        ax = fig.subplots()
    else:
        fig = ax.figure
    ax.plot([0, 1], [0, 1], linestyle=":", color="grey", label="ideal (coverage = alpha)")
    excess = []
    for i, curve in enumerate(curves):
        alphas = list(curve.get("alphas") or CREDIBLE_LEVELS)
        label = str(curve.get("label", f"curve {i}"))
        if curve.get("ece") is not None:
            label += f" (ECE {float(curve['ece']):.3f})"
        ax.plot(alphas, list(curve["coverage"]), marker="o", markersize=3,
                linestyle="--" if curve.get("dashed") else "-",
                color=curve.get("color", f"C{i % 10}"), label=_wrap(label, 60))  # fmt: skip
        excess.append(float(np.mean(np.asarray(curve["coverage"], float) - np.asarray(alphas))))
    ax.set(xlim=(-0.02, 1.02), ylim=(-0.02, 1.02), xlabel="credible level alpha",
           ylabel="coverage (targets inside)")  # fmt: skip
    ax.set_title(title or _reliability_title(curves), fontsize=10)
    ax.set_aspect("equal")
    ax.grid(True, alpha=0.3)
    if own:  # below the axes: a curve may run anywhere inside
        fig.legend(loc="outside lower center", fontsize=7, frameon=False)
    else:
        ax.legend(fontsize=7, loc="upper left")
    if (
        remedy
    ):  # in the triangle the curves leave empty: below a too-wide belief's, above a sharp one's
        wide = not excess or excess[0] >= 0
        x, y, ha, va = (0.98, 0.02, "right", "bottom") if wide else (0.02, 0.98, "left", "top")
        side = "too wide (covers more than alpha)" if wide else "too sharp (over-confident)"
        remedy = f"{side}: {remedy}"
        box = {"boxstyle": "round", "facecolor": "#fff3cd", "edgecolor": "#d4a017"}
        ax.text(x, y, _wrap(remedy, 40), transform=ax.transAxes, ha=ha, va=va, fontsize=7.5,
                bbox=box)  # fmt: skip
    _fit(fig)
    return fig


# ---------------------------------------------------------------------------------- OOD


def pr_figure(
    curves: Mapping[str, Sequence[Mapping[str, float]]], ax: Any = None, title: str | None = None
) -> Any:
    """Precision against recall of keeping clean pairs over the quantile q, one line per
    {label: rows of `rotlearn.ood.evaluation.precision_recall_curve`}; the q = 0.25 and 0.75
    points of the first curve are marked (the others' follow the same order)."""
    if ax is None:
        fig = new_figure(5.0, 4.0)
        ax = fig.subplots()
    else:
        fig = ax.figure
    for i, (label, rows) in enumerate(curves.items()):
        recall = [r["recall"] for r in rows]
        precision = [r["precision"] for r in rows]
        ax.plot(
            recall, precision, marker=".", markersize=3, color=f"C{i % 10}", label=_wrap(label, 30)
        )
        if i == 0:
            for r in rows:
                if any(math.isclose(r["q"], q) for q in (0.25, 0.75)):
                    ax.annotate(
                        f"q={r['q']:g}",
                        (r["recall"], r["precision"]),
                        fontsize=7,
                        xytext=(4, -10),
                        textcoords="offset points",
                    )
    ax.set(xlabel="recall % (clean pairs kept)", ylabel="precision % (kept pairs clean)")
    ax.set_title(_wrap(title or "precision-recall over q", 40), fontsize=9)
    if len(curves) > 1:
        ax.legend(fontsize=6.5, loc="lower left")
    _fit(fig)
    return fig


def scatter_figure(
    name: str,
    keep_below: bool,
    errors: np.ndarray,
    scores: np.ndarray,
    ood: np.ndarray,
    ax: Any = None,
    title: str | None = None,
) -> Any:
    """Score against error on a flagged test set, clean and OOD pairs apart.

    Args:
        name: the score; keep_below: its confident side (low or high).
        errors, scores: (N,) degrees and scores; ood: (N,) bool.
    """
    if ax is None:
        fig = new_figure(4.5, 3.5)
        ax = fig.subplots()
    else:
        fig = ax.figure
    ood = np.asarray(ood, bool)
    for flag, label in ((False, "clean"), (True, "OOD (erased)")):
        ax.scatter(
            np.asarray(scores)[ood == flag],
            np.asarray(errors)[ood == flag],
            s=5,
            alpha=0.6,
            label=label,
        )
    ax.set(
        xlabel=f"{name} ({'low' if keep_below else 'high'} = confident)",
        ylabel="error (deg, log scale)",
        yscale="log",
    )
    _plain_numbers(ax.yaxis)
    if title:
        ax.set_title(_wrap(title, 36), fontsize=9)
    ax.legend(fontsize=7)
    _fit(fig)
    return fig


def box_groups(name: str, sets: Mapping[str, Mapping[str, Any]]) -> dict[str, np.ndarray]:
    """The score `name` on the training, validation, test, erased, each extra set's OOD and
    pure-noise pairs (those present), finite values only: the groups of the box plots (paper
    Fig. 6c).

    Args:
        sets: as `rotlearn.ood.evaluation.score_sets` returns them ({set: {"error", score
            name: (N,), "corrupted": (N,) bool for flagged sets}}).
    """
    groups = {}
    for reference in ("train", "val"):
        if reference in sets:
            groups[reference] = sets[reference][name]
    if "clean" in sets:
        groups["test"] = sets["clean"][name]
    for set_name, data in sets.items():
        if set_name in ("train", "val", "clean", "noise") or "corrupted" not in data:
            continue
        flags = np.asarray(data["corrupted"], bool)
        groups["erased" if set_name == "corrupted" else set_name] = np.asarray(data[name])[flags]
    if "noise" in sets:
        groups["noise"] = sets["noise"][name]
    arrays = {k: np.asarray(v, float) for k, v in groups.items()}
    return {k: v[np.isfinite(v)] for k, v in arrays.items()}


def score_boxes_figure(
    name: str,
    keep_below: bool,
    groups: Mapping[str, np.ndarray],
    ax: Any = None,
    title: str | None = None,
) -> Any:
    """Box plots of a score per group of pairs (`box_groups`; paper Fig. 6c)."""
    if ax is None:
        fig = new_figure(4.5, 3.5)
        ax = fig.subplots()
    else:
        fig = ax.figure
    groups = {k: v for k, v in groups.items() if len(v)}
    ax.boxplot(list(groups.values()), showfliers=False)
    ax.set_xticks(range(1, len(groups) + 1), list(groups), fontsize=7, rotation=30, ha="right")
    ax.set_ylabel(name)
    side = "low" if keep_below else "high"
    ax.set_title(_wrap(title or f"{name} ({side} = confident)", 36), fontsize=9)
    _fit(fig)
    return fig


def examples_figure(images: Any, captions: Sequence[Mapping[str, Any]]) -> Any:
    """A grid of test pairs with their error and scores: one row per pair, its two frames side
    by side, the caption above.

    Args:
        images: (K, 2C, S, S) uint8 pairs (torch or numpy) as the network saw them before
            normalisation (erased where they are), C = 1 or 3.
        captions: per pair {"erased": bool, "error": degrees, <score name>: value, ...}.
    """
    images = np.asarray(images.cpu() if hasattr(images, "cpu") else images)
    k, channels = images.shape[0], images.shape[1] // 2
    fig = new_figure(4.4, 2.3 * k)
    axes = fig.subplots(k, 2, squeeze=False)
    for row, (pair, caption) in enumerate(zip(images, captions, strict=True)):
        for col in range(2):
            frame = pair[col * channels : (col + 1) * channels].transpose(1, 2, 0)
            ax = axes[row][col]
            ax.imshow(frame[..., 0] if channels == 1 else frame, cmap="gray", vmin=0, vmax=255)
            ax.set_xticks([])
            ax.set_yticks([])
        scores = ", ".join(
            f"{LABELS.get(key, key)} {value:.3g}"
            for key, value in caption.items()
            if key not in ("erased", "error")
        )
        kind = "erased" if caption.get("erased") else "clean"
        axes[row][0].set_title(
            _wrap(f"{kind}, err {caption['error']:.2f} deg: {scores}", 60), fontsize=7, loc="left"
        )
    _fit(fig)
    return fig


def sets_bars_figure(bars: Mapping[str, Sequence[float]], set_labels: Sequence[str]) -> Any:
    """Paper Fig. 8b: the mean error of the kept pairs on each test set, one bar per method
    ({label: one height per set, NaN where absent})."""
    fig = new_figure(2.5 + 2.2 * len(set_labels), 4.4)
    ax = fig.subplots()
    width = 0.8 / max(len(bars), 1)
    for i, (label, heights) in enumerate(bars.items()):
        x = np.arange(len(set_labels)) + (i - (len(bars) - 1) / 2) * width
        ax.bar(x, heights, width=width * 0.95, label=label, color=f"C{i % 10}")
    ax.set_xticks(range(len(set_labels)), [_wrap(s, 18) for s in set_labels], fontsize=8)
    ax.set(ylabel="mean error of kept pairs (deg)")
    ax.grid(True, axis="y", alpha=0.3)
    fig.legend(loc="outside right upper", fontsize=7, frameon=False)
    _fit(fig)
    return fig
