"""Figures of beliefs (rotlearn.plots): the reliability diagram's content."""

from __future__ import annotations

from rotlearn.bingham import CREDIBLE_LEVELS
from rotlearn.plots import reliability_figure


def test_the_reliability_diagram_draws_the_diagonal_each_curve_and_the_ece():
    curve = [min(1.0, a + 0.1) for a in CREDIBLE_LEVELS]
    curves = [{"label": "A", "coverage": curve, "ece": 0.0888},
              {"label": "B", "coverage": CREDIBLE_LEVELS, "dashed": True}]  # fmt: skip
    fig = reliability_figure(curves)
    (ax,) = fig.axes
    diagonal, a, b = ax.get_lines()
    assert list(diagonal.get_xdata()) == [0, 1] == list(diagonal.get_ydata())
    assert list(a.get_xdata()) == list(CREDIBLE_LEVELS) and list(a.get_ydata()) == curve
    assert b.get_linestyle() == "--" and a.get_linestyle() == "-"
    assert ax.get_title() == "ECE 0.089"
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [
        "calibrated", "A (ECE 0.089)", "B"]  # fmt: skip
    one = reliability_figure([{"label": "A", "coverage": curve, "ece": 0.01},
                              {"label": "B", "coverage": curve, "ece": 0.2}])  # fmt: skip
    assert one.axes[0].get_title() == "ECE 0.010 (A), 0.200 (B)"
