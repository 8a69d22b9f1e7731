"""The figures a person reads (rotlearn.report.figures): what each draws, axes in plain numbers
and whole epochs, titles that fit, and the reliability diagram's advice."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from rotlearn.bingham import CREDIBLE_LEVELS
from rotlearn.report.figures import (
    calibration_remedy,
    curves_figure,
    reliability_figure,
    save_figure,
)


def _rendered(fig):
    """The figure drawn on an Agg canvas (layout done), as saving it does."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig).draw()
    return fig


def _overlap(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


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
    assert ax.get_title() == "reliability: ECE 0.089"
    assert [t.get_text() for t in fig.legends[0].get_texts()] == [
        "ideal (coverage = alpha)", "A (ECE 0.089)", "B"]  # fmt: skip
    two = reliability_figure([{"label": "A", "coverage": curve, "ece": 0.01},
                              {"label": "B", "coverage": curve, "ece": 0.2}])  # fmt: skip
    assert two.axes[0].get_title() == "reliability of the credible regions"
    # a curve on the frame (a belief far too wide covers every target) stays visible
    low, high = ax.get_ylim()
    assert low < 0 and high > 1


def test_an_uncalibrated_belief_names_its_remedy_and_every_text_fits():
    wide = [1.0] * len(CREDIBLE_LEVELS)  # the chordal A head: coverage 1 at every level
    remedy = calibration_remedy(0.5, tempered=False, likelihood=False, rep="a")
    assert "calibrate=true" in remedy and "loss=bingham" in remedy
    assert "loss=fisher_nll" in calibration_remedy(0.5, False, False, rep="fisher")
    calibrated = calibration_remedy(0.3, tempered=True, likelihood=False)
    assert "calibrate=true" not in calibrated  # it was: its note says calibration fell short
    assert calibrated.startswith("still miscalibrated after calibration (ECE 0.30 > 0.1)")
    assert calibration_remedy(0.05, tempered=False, likelihood=False) is None
    label = "T = 0.503367 with a long label that would be clipped in a title"
    fig = _rendered(reliability_figure([{"label": label, "coverage": wide, "ece": 0.5}],
                                       remedy=remedy))  # fmt: skip
    (ax,) = fig.axes
    note = next(t for t in ax.texts if "calibrate=true" in t.get_text())
    renderer = fig.canvas.get_renderer()
    frame = fig.bbox
    for artist in (ax.title, note, fig.legends[0], ax.xaxis.label, ax.yaxis.label):
        box = artist.get_window_extent(renderer)
        assert (
            frame.x0 <= box.x0 and box.x1 <= frame.x1 and frame.y0 <= box.y0 and box.y1 <= frame.y1
        )
    curve = ax.get_lines()[1].get_window_extent(renderer)  # the curve on the frame at 1.0
    assert not _overlap(note.get_window_extent(renderer), curve)
    assert not _overlap(fig.legends[0].get_window_extent(renderer), ax.get_window_extent(renderer))
    # with a report's two curves (a legend of three rows) the title kept off the top edge (it
    # touched it: the square plot and its legend overflowed the figure's height)
    two = [{"label": "a", "coverage": wide, "ece": 0.5}, {"label": "a at T = 1", "coverage": wide}]
    fig = _rendered(reliability_figure(two, remedy=remedy))
    title = fig.axes[0].title.get_window_extent(fig.canvas.get_renderer())
    assert fig.bbox.y1 - title.y1 >= 5  # pixels of margin


def test_curves_show_whole_epochs_plain_numbers_and_one_legend_entry_per_group(tmp_path):
    rng = np.random.default_rng(0)
    runs = {"a optim.lr=0.001": [60 / np.arange(1, 6) + rng.random(5) for _ in range(3)],
            "sixd optim.lr=0.001": [80 / np.arange(1, 6)]}  # fmt: skip
    fig = _rendered(curves_figure({"val: mean error (deg)": runs}))
    (ax,) = fig.axes
    ticks = [t for t in ax.get_xticks() if ax.get_xlim()[0] <= t <= ax.get_xlim()[1]]
    assert ticks and all(float(t).is_integer() for t in ticks)
    labels = [t.get_text() for t in ax.get_yticklabels() + ax.get_yticklabels(minor=True)]
    shown = [t for t in labels if t]
    assert shown and all("^" not in t and "times" not in t for t in shown)
    assert all(float(t) > 0 for t in shown)  # plain numbers such as 20, 50
    assert ax.get_ylabel() == "error (deg, log scale)"  # a log axis says so
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert legend == ["a optim.lr=0.001 (median of 3)", "sixd optim.lr=0.001"]
    path = save_figure(fig, tmp_path / "curves.png")
    assert Image.open(path).size[0] > 300
    assert curves_figure({"val": {"a": []}}) is None


@pytest.mark.filterwarnings("ignore:constrained_layout not applied")  # a 400-letter label
@pytest.mark.parametrize("label", ["$" + "\\sqrt{" * 200 + "x" + "}" * 200 + "$", "$\\nosuchcmd{$"])
def test_a_label_is_drawn_as_written_not_read_as_tex_math(tmp_path, label):
    """Labels come from config values, a received run's too: matplotlib read `$...$` as TeX math,
    and a nested one raised RecursionError (an unknown command ParseFatalException) midway
    through rotlearn-report, which left summary.csv without report.md."""
    from rotlearn.report.figures import error_boxes_figure, score_boxes_figure

    runs = {f"a data.camera={label}": [np.array([3.0, 2.0, 1.0])]}
    curves = curves_figure({f"val {label}": runs})
    boxes = error_boxes_figure({label: {label: np.array([1.0, 2.0, 3.0])}}, label)
    scores = score_boxes_figure(
        "dt", True, {label: np.array([1.0, 2.0]), "val": np.array([0.5, 1.5])}
    )
    for name, fig in {"curves": curves, "boxes": boxes, "scores": scores}.items():
        save_figure(fig, tmp_path / f"{name}.png")
        texts = [t.get_text() for t in fig.findobj(lambda a: hasattr(a, "get_parse_math"))]
        assert any(label in t for t in texts), name
    assert [t.get_text() for t in curves.legends[0].get_texts()] == [f"a data.camera={label}"]


def test_a_text_longer_than_max_text_is_cut_and_keeps_apart_from_its_neighbour():
    """A received config value of 100000 characters took 50 s to draw in a legend; a figure's
    text is cut to MAX_TEXT characters, ending in a hash of the whole."""
    from rotlearn.report.figures import MAX_TEXT

    long = "a note=" + "A" * 100_000
    runs = {long + "1": [np.array([3.0, 2.0])], long + "2": [np.array([2.0, 1.0])]}
    legend = [t.get_text() for t in curves_figure({"val": runs}).legends[0].get_texts()]
    assert all(len(t) == MAX_TEXT and t.startswith("a note=AAA") for t in legend)
    assert len(set(legend)) == 2  # the hashes tell the two apart


def test_a_curve_of_millions_of_epochs_is_drawn_at_max_points_first_and_last_kept(tmp_path):
    """A received run's metrics log of 2 million epochs (38 MB, within the read bound) made
    Agg raise OverflowError (cell block limit) midway through rotlearn-report."""
    from rotlearn.report.figures import MAX_POINTS

    values = 1.0 + np.arange(2_000_000) % 7
    fig = curves_figure({"val": {"a": [values, values + 1]}})
    save_figure(fig, tmp_path / "curves.png")
    (line,) = fig.axes[0].get_lines()
    epochs = line.get_xdata()
    assert len(epochs) == MAX_POINTS and epochs[0] == 1 and epochs[-1] == len(values)
    assert np.all(np.diff(epochs) > 0)
    short = curves_figure({"val": {"a": [np.array([3.0, 2.0, 1.0])]}})
    assert list(short.axes[0].get_lines()[0].get_xdata()) == [1, 2, 3]  # every epoch


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_a_saved_figure_follows_the_umask(tmp_path, umask):
    import os

    old = os.umask(umask)
    try:
        path = save_figure(reliability_figure([{"coverage": CREDIBLE_LEVELS}]), tmp_path / "r.png")
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask
    assert [p.name for p in tmp_path.iterdir()] == ["r.png"]  # no temporary file left
