"""``magail-sumo report``: HTML / Markdown / CSV report of an evaluation folder."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from magail_sumo.outputs import OutputError, printable
from magail_sumo.cli.progress import PhaseBars


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="report of a magail-sumo evaluate folder",
                       description="Score DIR (traffic metrics and WOSAC realism per scene and "
                                   "method) and write DIR/report/report.html (self-contained), "
                                   "report.md, metrics.csv and summary.csv; city results of "
                                   "evaluate --city (DIR/city.json) add a table and city.csv. "
                                   "Bad rollouts are reported on stderr and the rest is still "
                                   "scored.")
    p.add_argument("folder", type=Path, metavar="DIR", help="folder written by evaluate")
    p.add_argument("--out", type=Path, metavar="OUT", help="report folder (default DIR/report; "
                   "new, empty or written by magail-sumo)")
    p.add_argument("--submission", nargs=2, action="append", default=[],
                   metavar=("NAME", "FILE.binproto"),
                   help="also score an external SimAgentsChallengeSubmission as method NAME "
                        "(repeatable)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="processes scoring the scenes and methods (default: up to 2, one per "
                        "core; 1: in this process)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
    from magail_sumo.evaluation.report import build_report

    subs: dict[str, list[str]] = {}
    for name, path in args.submission:
        subs.setdefault(name, []).append(path)
    bars = PhaseBars()
    try:
        res = build_report(args.folder, args.out, subs, args.workers, progress=bars)
    except OSError as exc:  # a full disk, a read-only folder: one line, no traceback
        raise OutputError(f"{exc.filename or args.out or args.folder}: cannot write "
                          f"({exc.strerror or type(exc).__name__})") from None
    finally:
        bars.close()
    for e in res.errors:
        print(f"error: {e if e.isprintable() else printable(e, 2000)}", file=sys.stderr)
    city = f", {res.city_csv.name}" if res.city_csv is not None else ""
    print(f"report: {res.html} ({res.markdown.name}, {res.metrics_csv.name}, "
          f"{res.summary_csv.name}{city})", file=sys.stderr)
    return 1 if res.errors else 0
