"""Seconds to build the evaluation report of an evaluate folder (median over repeats).

    python benchmarks/report.py EVAL_DIR [--repeats 3] [--workers N] [--root REPO]

Each run writes the whole report (scoring, figures, animations, files) into a fresh folder and
prints its wall time and its CPU time (this process and its scoring workers; on a machine busy
with other work the CPU time is the steadier figure). ``--root`` imports magail_sumo from
another checkout (to compare before / after).
Goal (issue 14): a 5-scene x 5-method report (32 rollouts) in <= 30 s.
"""

from __future__ import annotations

import argparse
import inspect
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path


def _cpu() -> float:
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


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

    kw = {}
    if args.workers is not None and "workers" in inspect.signature(build_report).parameters:
        kw["workers"] = args.workers
    walls, cpus = [], []
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as tmp:
            t0, c0 = time.perf_counter(), _cpu()
            res = build_report(args.folder, Path(tmp) / "report", **kw)
            walls.append(time.perf_counter() - t0)
            cpus.append(_cpu() - c0)
        print(f"report {walls[-1]:.1f} s wall, {cpus[-1]:.1f} s CPU", flush=True)
    sc = res.scores
    print(f"{len(sc.scenes)} scenes x {len(sc.methods)} methods ({len(sc.rows)} pairs, "
          f"{len(res.errors)} error(s)): median {statistics.median(walls):.1f} s wall, "
          f"{statistics.median(cpus):.1f} s CPU (goal <= 30 s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
