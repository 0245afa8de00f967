"""Seconds to build the evaluation report of an evaluate folder (median over repeats).

    python benchmarks/report.py EVAL_DIR [--repeats 3] [--workers N] [--root REPO]

Prints the time of scoring (``collect``: reading rollouts, realism and traffic metrics) and of
the whole ``build_report`` (scoring, figures, animations, files), each run into a fresh
folder. ``--root`` imports magail_sumo from another checkout (to compare before / after).
Goal (issue 14): a 5-scene x 5-method report (32 rollouts) in <= 30 s.
"""

from __future__ import annotations

import argparse
import inspect
import statistics
import sys
import tempfile
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--workers", type=int, default=None,
                    help="scoring processes (default: build_report's default)")
    ap.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1])
    args = ap.parse_args()
    sys.path.insert(0, str(args.root.resolve()))
    from magail_sumo.evaluation.report import build_report
    from magail_sumo.evaluation.report.scoring import collect

    kw = {}
    if args.workers is not None and "workers" in inspect.signature(build_report).parameters:
        kw["workers"] = args.workers
    score_s, total_s = [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        sc = collect(args.folder, **kw)
        score_s.append(time.perf_counter() - t0)
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            build_report(args.folder, Path(tmp) / "report", **kw)
            total_s.append(time.perf_counter() - t0)
        print(f"scoring {score_s[-1]:.1f} s, whole report {total_s[-1]:.1f} s", flush=True)
    pairs = len(sc.rows)
    print(f"{len(sc.scenes)} scenes x {len(sc.methods)} methods ({pairs} pairs): median scoring "
          f"{statistics.median(score_s):.1f} s ({statistics.median(score_s) / max(pairs, 1):.2f} s "
          f"per pair), median report {statistics.median(total_s):.1f} s (goal <= 30 s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
