"""rotlearn-report reads run directories as untrusted files: bounded, never hanging, a damaged
file named in a warning and its run still listed (issue 22)."""

from __future__ import annotations

import os

from rotlearn.report import collect_runs, make_report
from tests.conftest import copy_run, tree_hashes, within

ALIAS_BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [" + ", ".join([f"*{p}"] * 9) + "]\n"
    for p, c in zip("abcdefgh", "bcdefghi", strict=True)
)  # 890 bytes; 387 million strings once expanded (7.5 GB in the report's flattening)


def _fifo(path):
    path.unlink(missing_ok=True)
    os.mkfifo(path)


# one crafted run per entry: what is written into it, and the warning that names it
CRAFTED = {
    "alias-bomb": (lambda run: (run / ".hydra" / "config.yaml").write_text(ALIAS_BOMB),
                   "YAML alias"),
    "huge-overrides": (lambda run: (run / ".hydra" / "overrides.yaml").write_text(
        "- a=1\n" * 3_500_000), "too large"),
    "status-fifo": (lambda run: _fifo(run / "status.json"), "named pipe"),
    "metrics-fifo": (lambda run: _fifo(run / "metrics.json"), "named pipe"),
    "csv-fifo": (lambda run: _fifo(run / "csv" / "metrics.csv"), "named pipe"),
    "status-list": (lambda run: (run / "status.json").write_text("[1, 2]"), "not a JSON object"),
    "status-deep": (lambda run: (run / "status.json").write_text("[" * 100_000 + "]" * 100_000),
                    "nested too deeply"),
}  # fmt: skip


def test_a_report_over_crafted_runs_is_bounded_and_names_them(finished_run, tmp_path, caplog):
    """Each of these made the landed report hang, grow to gigabytes, or fail with an
    AttributeError or a RecursionError."""
    sweep = tmp_path / "sweep"
    copy_run(finished_run, sweep / "good")
    for name, (craft, _) in CRAFTED.items():
        craft(copy_run(finished_run, sweep / name))
    before = tree_hashes(tmp_path, skip=sweep)
    with within(120), caplog.at_level("WARNING", logger="rotlearn"):
        runs = collect_runs(sweep)
        files = make_report(sweep)
    assert sorted(runs["job"]) == sorted(["good", *CRAFTED])
    warnings = [r.getMessage() for r in caplog.records]
    for name, (_, warning) in CRAFTED.items():
        assert any(str(sweep / name) in w and warning in w for w in warnings), (name, warnings)
    assert files["report"].is_file()
    assert tree_hashes(tmp_path, skip=sweep) == before
