"""rotlearn-report reads run directories as untrusted files: bounded, never hanging, a damaged
file named in a warning and the run still listed (issue 22)."""

from __future__ import annotations

import os

import pytest

from rotlearn.cli.report import collect_runs, make_report
from tests.conftest import copy_run, tree_hashes, within

ALIAS_BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [" + ", ".join([f"*{p}"] * 9) + "]\n"
    for p, c in zip("abcdefgh", "bcdefghi", strict=True)
)


def _fifo(path):
    path.unlink(missing_ok=True)
    os.mkfifo(path)


CRAFTED = {
    "config.yaml an alias bomb": (
        lambda run: (run / ".hydra" / "config.yaml").write_text(ALIAS_BOMB),
        "YAML alias",
    ),
    "overrides.yaml of 20 MB": (
        lambda run: (run / ".hydra" / "overrides.yaml").write_text("- a=1\n" * 3_500_000),
        "too large",
    ),
    "status.json a named pipe": (lambda run: _fifo(run / "status.json"), "named pipe"),
    "metrics.json a named pipe": (lambda run: _fifo(run / "metrics.json"), "named pipe"),
    "csv/metrics.csv a named pipe": (lambda run: _fifo(run / "csv" / "metrics.csv"), "named pipe"),
    "status.json a list": (lambda run: (run / "status.json").write_text("[1, 2]"), "not a JSON"),
    "status.json nested 100k deep": (
        lambda run: (run / "status.json").write_text("[" * 100_000 + "]" * 100_000),
        "nested too deeply",
    ),
}


@pytest.mark.parametrize("name", sorted(CRAFTED))
def test_a_report_over_a_crafted_run_is_bounded(finished_run, tmp_path, caplog, name):
    sweep = tmp_path / "sweep"
    good = copy_run(finished_run, sweep / "0")
    bad = copy_run(finished_run, sweep / "1")
    craft, warning = CRAFTED[name]
    craft(bad)
    before = tree_hashes(tmp_path, skip=sweep)
    with within(60), caplog.at_level("WARNING", logger="rotlearn"):
        runs = collect_runs(sweep)
        files = make_report(sweep)
    assert sorted(runs["job"]) == ["0", "1"]
    assert warning in caplog.text and str(bad) in caplog.text
    assert files["report"].is_file() and str(good) in set(runs["dir"])
    assert tree_hashes(tmp_path, skip=sweep) == before
