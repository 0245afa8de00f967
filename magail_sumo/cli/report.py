"""``magail-sumo report``: HTML / Markdown / CSV report of an evaluation folder."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="report of a magail-sumo evaluate folder",
                       description="Score DIR (traffic metrics and WOSAC realism per scene and "
                                   "method) and write DIR/report/report.html (self-contained), "
                                   "report.md, metrics.csv and summary.csv. Bad rollouts are "
                                   "reported on stderr and the rest is still scored.")
    p.add_argument("folder", type=Path, metavar="DIR", help="folder written by evaluate")
    p.add_argument("--out", type=Path, metavar="OUT", help="report folder (default DIR/report)")
    p.add_argument("--submission", nargs=2, action="append", default=[],
                   metavar=("NAME", "FILE.binproto"),
                   help="also score an external SimAgentsChallengeSubmission as method NAME "
                        "(repeatable)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from magail_sumo.evaluation.report import build_report

    subs: dict[str, list[str]] = {}
    for name, path in args.submission:
        subs.setdefault(name, []).append(path)
    res = build_report(args.folder, args.out, subs)
    for e in res.errors:
        print(f"error: {e}", file=sys.stderr)
    print(f"report: {res.html} ({res.markdown.name}, {res.metrics_csv.name}, "
          f"{res.summary_csv.name})", file=sys.stderr)
    return 1 if res.errors else 0
