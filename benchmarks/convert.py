"""Seconds per scene per conversion stage (median over repeats), netconvert and SUMO run included.

    python benchmarks/convert.py [--repeats 5] [FILE...]

Goal (issue 3): <= 2 s per scene on one core.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from converters import iter_scenes  # noqa: E402
from converters.sumo import convert_scene  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*", type=Path,
                    default=sorted((ROOT / "data" / "womd").glob("*.tfrecord")))
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    scenes = list(iter_scenes(args.files))
    stages: list[str] = []
    print(f"{'scene':18s} " + "median seconds per stage", flush=True)
    totals = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in scenes:
            runs = [convert_scene(scene, Path(tmp)) for _ in range(args.repeats)]
            bad = [r.reason for r in runs if r.status != "ok"]
            if bad:
                print(f"{scene.scenario_id}: failed: {bad[0]}")
                continue
            stages = list(runs[0].timings)
            med = {s: statistics.median(r.timings[s] for r in runs) for s in stages}
            totals.append(med["total"])
            print(f"{scene.scenario_id:18s} " + "  ".join(f"{s}={med[s]:.3f}" for s in stages),
                  flush=True)
    if totals:
        print(f"median total per scene: {statistics.median(totals):.3f} s "
              f"(max {max(totals):.3f} s; goal <= 2 s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
