"""`rotlearn-report <sweep dir> [<sweep dir> ...]`: summary.csv, report.md and figures of a sweep
(or of several, pooled into one report, e.g. a sweep and a run beside it), made from its run
directories alone (`rotlearn.report.make_report`).

Runs are grouped by every config key whose value differs between them, except the trial keys
the sweep declares (`report.trial_keys`: the stratified lr trials of `sweep=lr` and their seeds;
seeds by default): a 2 x 2 sweep `rep=a,sixd optim.lr=1e-4,1e-3` gives four settings, each a
row of the tables and a curve of the plots. `--group-by KEY ...` groups by exactly those keys
(a config group such as `rep`, or a key such as `optim.lr`), pooling the rest; `--pool KEY ...`
pools more keys as trials.

  rotlearn-report outputs/multirun/<time>
  rotlearn-report outputs/multirun/<time> --group-by rep        # one row per head, lr pooled
  rotlearn-report outputs/multirun/<time> outputs/runs/<time> --out outputs/report
"""

from __future__ import annotations

import argparse
import sys

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """Entry point of `rotlearn-report`; 0 when the report was written, 2 when there are no
    runs to report on."""
    parser = argparse.ArgumentParser(
        prog="rotlearn-report",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "sweep_dir", nargs="+", help="a multirun (or single run) directory; several: pooled"
    )
    parser.add_argument("--out", help="where to write (default: the first sweep directory)")
    parser.add_argument(
        "--group-by", nargs="+", metavar="KEY", help="group runs by exactly these config keys"
    )
    parser.add_argument(
        "--pool", nargs="+", metavar="KEY", default=[], help="pool these keys as trials"
    )
    args = parser.parse_args(argv)
    from rotlearn.report import make_report

    try:
        files = make_report(args.sweep_dir, args.out, group_by=args.group_by, pool=args.pool)
    except (OSError, ValueError) as exc:  # a failed write (a full disk); ValueError: --group-by
        print(f"rotlearn-report: {exc}", file=sys.stderr)
        return 2
    for name, path in files.items():
        print(f"{name:12s} {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
