"""Sensor-suite throughput: ``SensorSuite.observe`` of every valid road user of a log step.

Per bundled WOMD scene and layout (``ego``, ``seed``, ``ego`` + route command), the median time
of one ``observe`` call (µs) and agents observed per second; ``crowd``: the boxes copied 3.3 m
apart to more than 300 (the grid lidar path). Inputs are the log's boxes at the middle step,
random previous actions (seeded), the log's last state as destination.

``--code DIR`` imports ``magail_sumo`` from another checkout (same API: ``SensorSuite(scene,
config)``, ``Boxes``, ``EgoState``) for paired before/after runs on the same machine, e.g.
``--code /path/to/old/checkout`` then without it; ``--pairs N`` alternates them N times in
fresh processes and prints the median new/old time ratio per case.

    python benchmarks/sensor_suite.py [--json] [--repeats N] [--code DIR] [--pairs N --old DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENES = ("637f20cafde22ff8", "2831b6fde0420b0d", "850c48d8bbfa008f")


def _inputs(scene, crowd: bool):
    from magail_sumo.sensors.observation import Boxes, EgoState

    tr = scene.tracks
    t = tr.valid.shape[1] // 2
    r = np.flatnonzero(tr.valid[:, t])
    cols = [tr.x[r, t].astype(float), tr.y[r, t].astype(float), tr.heading[r, t].astype(float),
            tr.length[r, t].astype(float), tr.width[r, t].astype(float)]
    if crowd:
        reps = 300 // max(len(r), 1) + 1
        cols = [np.concatenate([v + (3.3 * j if i < 2 else 0.0) for j in range(reps)])
                for i, v in enumerate(cols)]
    n = len(cols[0])
    rows = np.resize(r, n)
    ego = EgoState(np.arange(n), np.hypot(tr.vx[rows, t], tr.vy[rows, t]).astype(float),
                   np.random.default_rng(0).uniform(-1, 1, (n, 2)),
                   np.stack([tr.x[rows, -1], tr.y[rows, -1]], 1),
                   tr.heading[rows, -1].astype(float))
    return Boxes(*cols), ego, t


def measure(repeats: int) -> dict[str, dict[str, float]]:
    """{case: {"agents", "us_per_observe", "agents_per_s"}} of the imported checkout."""
    from converters import load_scene
    from magail_sumo.sensors.observation import ObservationConfig, SensorSuite

    layouts = {"ego": ObservationConfig(), "seed": ObservationConfig(layout="seed"),
               "ego_command": ObservationConfig(command=True)}
    out = {}
    for sid in SCENES:
        scene = load_scene(ROOT / "data" / "womd" / f"{sid}.tfrecord")
        for name, cfg in layouts.items():
            suite = SensorSuite(scene, cfg)
            for crowd in (False, True) if name == "ego" else (False,):
                boxes, ego, t = _inputs(scene, crowd)
                suite.observe(boxes, ego, t)  # compile / warm caches
                clock = time.perf_counter()
                suite.observe(boxes, ego, t)
                calls = int(np.clip(0.02 / (time.perf_counter() - clock), 1, 20))  # ~20 ms
                times = []
                for _ in range(repeats):
                    clock = time.perf_counter()
                    for _ in range(calls):
                        suite.observe(boxes, ego, t)
                    times.append((time.perf_counter() - clock) / calls)
                us = float(np.median(times)) * 1e6
                a = len(ego.index)
                out[f"{sid}/{name}{'/crowd' if crowd else ''}"] = {
                    "agents": a, "us_per_observe": round(us, 1),
                    "agents_per_s": round(a / us * 1e6)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--code", type=Path, default=ROOT, help="checkout to import magail_sumo from")
    ap.add_argument("--pairs", type=int, default=0, help="paired runs against --old")
    ap.add_argument("--old", type=Path, help="the other checkout of a paired run")
    args = ap.parse_args()
    if args.pairs:
        if args.old is None:
            ap.error("--pairs needs --old DIR")
        ratios: dict[str, list[float]] = {}
        for k in range(args.pairs):
            runs = {}
            for label in (("old", "new") if k % 2 == 0 else ("new", "old")):
                code = args.old if label == "old" else ROOT
                cmd = [sys.executable, __file__, "--json", "--repeats", str(args.repeats),
                       "--code", str(code)]
                runs[label] = json.loads(subprocess.run(cmd, check=True, capture_output=True,
                                                        text=True).stdout)
            for case in runs["new"]:
                ratios.setdefault(case, []).append(runs["new"][case]["us_per_observe"]
                                                   / runs["old"][case]["us_per_observe"])
        for case, r in ratios.items():
            print(f"{case:36s} median new/old time {np.median(r):.3f} "
                  f"(min {min(r):.3f}, max {max(r):.3f}, {len(r)} pairs)")
        return
    sys.path.insert(0, str(args.code))
    import magail_sumo

    if not Path(magail_sumo.__file__).resolve().is_relative_to(args.code.resolve()):
        sys.exit(f"magail_sumo imported from {magail_sumo.__file__}, not from {args.code}")
    res = measure(args.repeats)
    if args.json:
        print(json.dumps(res))
        return
    for case, r in res.items():
        print(f"{case:36s} {r['agents']:4d} agents  {r['us_per_observe']:9.1f} µs/observe  "
              f"{r['agents_per_s']:8d} agents/s (median of {args.repeats})")


if __name__ == "__main__":
    main()
