"""Figures of beliefs, as matplotlib `Figure`s (no pyplot state, no files): drawn by the
regressor into TensorBoard and by `rotlearn-report` into PNG files.

`reliability_figure`: the reliability diagram of credible regions, coverage against credible
level alpha with the diagonal of a calibrated belief (`rotlearn.bingham.calibration`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from rotlearn.bingham.calibration import CREDIBLE_LEVELS

__all__ = ["reliability_figure"]


def _title(curves: Sequence[Mapping[str, Any]]) -> str:
    eces = [(c.get("label", ""), c.get("ece")) for c in curves if c.get("ece") is not None]
    if not eces:
        return "reliability of the credible regions"
    if len(eces) > 2:
        return "reliability of the credible regions (ECE in the legend)"
    return "ECE " + ", ".join(
        f"{ece:.3f}" + (f" ({label})" if len(eces) > 1 else "") for label, ece in eces
    )


def reliability_figure(
    curves: Sequence[Mapping[str, Any]], ax: Any = None, title: str | None = None
) -> Any:
    """Coverage of the highest-density credible regions against their level alpha, one line per
    curve, the diagonal coverage = alpha of a calibrated belief dashed in grey: below the
    diagonal the belief is over-confident (too sharp), above it too wide.

    Args:
        curves: each {"label": str, "coverage": [fraction per alpha], "alphas": the levels
            (default `CREDIBLE_LEVELS`), "ece": float (optional; shown in the legend and, for
            one or two curves, the title), "color": a matplotlib colour (optional),
            "dashed": bool (optional)}.
        ax: draw into this axes (its figure is returned); None: a new 4.5 x 4 inch figure.
        title: None: the ECE of each curve (`_title`).

    Returns:
        The matplotlib Figure.
    """
    if ax is None:
        from matplotlib.figure import Figure

        fig = Figure(figsize=(4.5, 4.0), dpi=100)
        ax = fig.subplots()
    else:
        fig = ax.figure
    ax.plot([0, 1], [0, 1], linestyle=":", color="grey", label="calibrated")
    for i, curve in enumerate(curves):
        alphas = list(curve.get("alphas") or CREDIBLE_LEVELS)
        label = str(curve.get("label", f"curve {i}"))
        if curve.get("ece") is not None:
            label += f" (ECE {float(curve['ece']):.3f})"
        ax.plot(alphas, list(curve["coverage"]), marker="o", markersize=3,
                linestyle="--" if curve.get("dashed") else "-",
                color=curve.get("color", f"C{i % 10}"), label=label)  # fmt: skip
    ax.set(xlim=(0, 1), ylim=(0, 1), xlabel="credible level alpha",
           ylabel="coverage (targets inside)", title=title or _title(curves))  # fmt: skip
    ax.set_aspect("equal")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    return fig
