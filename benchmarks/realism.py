"""Benchmark: seconds to score one scene's 32 rollouts with the WOSAC 2025 realism metrics.

Scores the bundled constant-velocity submission on scene 637f20cafde22ff8 (features of the log
and all 32 rollouts, likelihoods, meta-metric, ADE, rates), ``--repeats`` times after one
warm-up (numba compilation), and prints the median next to the official TensorFlow tool's time
for the same scene on the development machine (2-core CPU; it is not run here: issue 6 quotes
~150 s, and a later run of its feature + metric step on this machine took 246-287 s).

    python benchmarks/realism.py [--repeats 7] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from converters import load_scene  # noqa: E402
from magail_sumo.evaluation import read_submission  # noqa: E402
from magail_sumo.evaluation.realism import scenario_metrics  # noqa: E402

SCENE = ROOT / "data" / "womd" / "637f20cafde22ff8.tfrecord"
SUBMISSION = ROOT / "data" / "wosac" / "constvel_637f20cafde22ff8.binproto"
#: Official waymo-open-dataset tool (TF 2.12, CPU), same scene and submission, this machine.
OFFICIAL_SECONDS = 150.0
GOAL_SECONDS = 2.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    scene = load_scene(SCENE)
    t = time.perf_counter()
    (ro,) = read_submission(SUBMISSION)
    read_s = time.perf_counter() - t
    scenario_metrics(scene, ro)  # warm-up: numba compilation / cache load
    times = []
    for _ in range(args.repeats):
        t = time.perf_counter()
        scenario_metrics(scene, ro)
        times.append(time.perf_counter() - t)
    med = statistics.median(times)
    res = {"scene": scene.scenario_id, "rollouts": ro.shape[0], "agents": ro.shape[1],
           "repeats": args.repeats, "median_s": round(med, 3), "min_s": round(min(times), 3),
           "read_submission_s": round(read_s, 3), "official_s": OFFICIAL_SECONDS,
           "speedup": round(OFFICIAL_SECONDS / med, 1), "goal_s": GOAL_SECONDS,
           "goal_met": med <= GOAL_SECONDS}
    if args.json:
        print(json.dumps(res))
    else:
        print(f"realism, scene {res['scene']} ({res['rollouts']} rollouts × {res['agents']} "
              f"agents × 80 steps): median {med:.3f} s over {args.repeats} "
              f"(min {min(times):.3f} s; reading the submission {read_s:.3f} s)")
        print(f"official TensorFlow tool: ~{OFFICIAL_SECONDS:.0f} s  →  {res['speedup']}× "
              f"faster; goal ≤ {GOAL_SECONDS} s: {'met' if res['goal_met'] else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
