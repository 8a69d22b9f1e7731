"""Floor 4: reports of runs read from their directories alone.

`runs` collects run directories and groups them into settings; `tables` builds every table with
one function; `figures` draws every figure; `document.make_report` writes summary.csv, report.md
and the figures of a sweep (`rotlearn-report`, `rotlearn.cli.report`). `identity` says what
tells runs apart (their names and HPARAMS records), `tensorboard` where each metric lives in a
run's TensorBoard folder. `tables`, `figures`, `identity` and `tensorboard` import nothing above
floor 1, so the training callbacks draw and tabulate with them too.

Names are imported on first use (PEP 562): `from rotlearn.report import make_report`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rotlearn.report.document import make_report
    from rotlearn.report.runs import collect_runs

__all__ = ["collect_runs", "make_report"]


def __getattr__(name: str) -> Any:  # PEP 562
    if name == "make_report":
        from rotlearn.report.document import make_report

        return make_report
    if name == "collect_runs":
        from rotlearn.report.runs import collect_runs

        return collect_runs
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
