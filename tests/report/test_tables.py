"""The one table builder (rotlearn.report.tables.markdown_table) and the run's result table."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from rotlearn.report.tables import INFINITE_NOTE, markdown_table, results_table


def test_the_builder_rounds_marks_missing_values_and_escapes_cells():
    rows = [{"method": "a | b", "err": 1.23456, "n": 3, "q": None},
            {"method": "c\nd", "err": math.nan, "n": 4, "q": 0.75}]  # fmt: skip
    text = markdown_table(rows, ["method", ("err", "error (deg)"), "n", "q"],
                          formats={"q": "{:.1f}"})  # fmt: skip
    assert text.splitlines() == [
        "| method | error (deg) | n | q |",
        "|---|---|---|---|",
        "| a \\| b | 1.23 | 3 | - |",
        "| c d | - | 4 | 0.8 |",
    ]
    assert markdown_table(pd.DataFrame(rows)) == markdown_table(rows)


def test_an_infinite_value_is_said_to_be_one_below_the_table():
    """'inf' in a cell read like a very large number; the table now says what it is."""
    finite = [{"metric": "nll", "value": 1.5}]
    assert "inf:" not in markdown_table(finite)
    for value in (math.inf, -math.inf, np.float64(np.inf), np.float32(np.inf)):
        text = markdown_table([*finite, {"metric": "loss", "value": value}])
        assert text.splitlines()[-3:] == [f"| loss | {value:.2f} |", "", INFINITE_NOTE]


def test_a_runs_results_are_one_table_of_what_it_measured():
    metrics = {"test/err_mean": 2.5, "test/err_median": 1.25, "test/nll": -3.0, "test/ece": 0.04,
               "test/dt_spearman": 0.6, "test/dt_auroc_noisiest": 0.9, "ood/auroc_dt": 0.97,
               "epochs": 50, "diverged": False, "train/loss": 0.1}  # fmt: skip
    lines = results_table(metrics).splitlines()
    assert lines[0] == "| result | value |"
    assert "| test error, mean (deg) | 2.5 |" in lines and "| ECE | 0.04 |" in lines
    assert "| dt: Spearman with error | 0.6 |" in lines
    assert "| dt: AUROC, noisiest 10 % | 0.9 |" in lines
    assert "| OOD AUROC, dt | 0.97 |" in lines and "| diverged | no |" in lines
    assert not any("train" in line for line in lines)  # per-epoch series are curves, not results


def test_the_error_table_gives_one_runs_setting_its_numbers_once():
    """A setting of several runs gets the percentiles over them; where every setting has one
    run, p10, median and p90 were one number three times: the table gives it once."""
    from rotlearn.report.tables import percentile_table

    one = pd.DataFrame({"setting": ["a", "sixd"], "test/err_mean": [1.5, 2.5],
                        "test/err_median": [1.25, 2.25]})  # fmt: skip
    table = percentile_table(one).splitlines()
    assert table[0] == "| setting | test err mean | test err median |"
    assert table[2:] == ["| a | 1.500 | 1.250 |", "| sixd | 2.500 | 2.250 |"]
    seeds = pd.concat([one, one.assign(**{"test/err_mean": [2.5, 3.5]})])
    header = percentile_table(seeds).splitlines()[0]
    assert header == ("| setting | runs | test err mean: p10 | median | p90 | "
                      "median of per-run medians |")  # fmt: skip
