"""rotlearn.report.document's pieces that pool several runs of one setting (seeds)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rotlearn.report.document import _mean_curve


def test_the_precision_recall_curve_of_several_seeds_is_their_mean_at_each_q():
    """Seeds of one setting share one curve: at each q the mean recall, and the mean precision
    over the runs that keep a pair (a run that keeps none has no precision there). Before, the
    last seed's curve replaced the others' under the same label."""
    first = [{"q": 0.25, "recall": 20.0, "precision": math.nan},
             {"q": 0.75, "recall": 70.0, "precision": 90.0}]  # fmt: skip
    second = [{"q": 0.25, "recall": 30.0, "precision": 80.0},
              {"q": 0.75, "recall": 80.0, "precision": 70.0}]  # fmt: skip
    mean = _mean_curve([first, second])
    assert [r["q"] for r in mean] == [0.25, 0.75]
    assert mean[0]["recall"] == 25.0 and mean[0]["precision"] == 80.0
    assert mean[1] == {"q": 0.75, "recall": 75.0, "precision": pytest.approx(80.0)}
    nothing = [{"q": 0.25, "recall": 0.0, "precision": math.nan}]
    assert math.isnan(_mean_curve([nothing, nothing])[0]["precision"])
    assert _mean_curve([second]) == second  # one run: its own curve


def test_a_resumed_runs_curve_joins_its_csv_logs_the_latest_value_of_an_epoch_kept(
    tmp_path, monkeypatch
):
    """Each resume keeps the earlier CSV log in history/<n>/ (Lightning's CSVLogger deletes
    it); the curve reads them in n's order (10 after 9), then the run's own, an epoch logged
    again keeping its last value, and no more than the latest MAX_EARLIER_LOGS earlier ones:
    an epoch no log has is a gap at its own place (the values were drawn from epoch 1 on)."""
    import rotlearn.report.document as document

    def log(folder, rows):
        (folder / "csv").mkdir(parents=True)
        lines = [f"{epoch},{value}" for epoch, value in rows]
        (folder / "csv" / "metrics.csv").write_text("\n".join(["epoch,val/err_mean", *lines]))

    run = tmp_path / "run"
    log(run / "history" / "9", [(0, 50.0), (1, 40.0)])
    log(run / "history" / "10", [(2, 30.0)])
    log(run / "history" / "x", [(0, 99.0)])  # not an attempt's folder
    log(run, [(2, 20.0), (3, 10.0)])  # epoch 2 again: its last value
    assert list(document._curve(run, "val/err_mean")) == [50.0, 40.0, 20.0, 10.0]
    monkeypatch.setattr(document, "MAX_EARLIER_LOGS", 1)
    curve = document._curve(run, "val/err_mean")
    assert np.isnan(curve[:2]).all() and list(curve[2:]) == [20.0, 10.0]


def test_a_runs_csv_logs_are_read_within_one_logs_bound_and_odd_epochs_left_out(
    tmp_path, monkeypatch, caplog
):
    """65 logs of 64 MiB each, every one within the read bound of one, took 55 GiB to read
    together: they share that bound now, the newest read first; epochs that are no integer
    in [0, MAX_EPOCHS) (-5, 0.5, 1e300) were drawn as epochs 1, 2, 3."""
    import rotlearn.report.document as document
    from rotlearn.io import MAX_BYTES

    run = tmp_path / "run"
    for n in (1, 2):
        (run / "history" / str(n) / "csv").mkdir(parents=True)
        rows = f"epoch,val/err_mean\n{n - 1},{10.0 * n}\n"
        (run / "history" / str(n) / "csv" / "metrics.csv").write_text(rows)
    (run / "csv").mkdir()
    rows = "epoch,val/err_mean\n2,5.0\n-5,1.0\n0.5,1.0\n1e300,1.0\n"
    (run / "csv" / "metrics.csv").write_text(rows)
    assert list(document._curve(run, "val/err_mean")) == [10.0, 20.0, 5.0]
    assert "3 row(s) whose epoch is no integer" in caplog.text
    own = (run / "csv" / "metrics.csv").stat().st_size
    second = (run / "history" / "2" / "csv" / "metrics.csv").stat().st_size
    monkeypatch.setitem(MAX_BYTES, "metrics log", own + second)  # the oldest is over it
    curve = document._curve(run, "val/err_mean")
    assert np.isnan(curve[0]) and list(curve[1:]) == [20.0, 5.0]
    assert "over the read bound of a metrics log together" in caplog.text
