"""Conversion speed: seconds per scene per stage, or a whole shard's throughput and memory.

    python benchmarks/convert.py [--repeats 5] [FILE...]
    python benchmarks/convert.py --shard 500 [--workers 2] [--no-baseline] [--scene FILE]

Default mode: median seconds per conversion stage per scene (netconvert and the SUMO run
included). Goal (issue 3): <= 2 s per scene on one core.

``--shard N`` (issue 14): writes N copies of one real scene (default the small
850c48d8bbfa008f) into one WOMD TFRecord shard with the repo's writer, each copy under its own
scenario id (``<id>-00000`` ...; a repeated id would be a ``skipped`` row, converted once), and
converts the shard with :func:`converters.sumo.batch.convert_files` as ``magail-sumo convert``
does (a fresh worker process per scene). At 50, 250 and N scenes (and every 10 % in between) it
prints scenes/s per core and the peak RSS of the parent (also its current RSS) and of the
largest worker so far: flat memory means the parent's RSS does not grow with the scene count.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import resource
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from converters import iter_scenes, load_scene  # noqa: E402
from converters.sumo import convert_scene  # noqa: E402


def stages(args: argparse.Namespace) -> int:
    scenes = list(iter_scenes(args.files))
    stage_names: list[str] = []
    print(f"{'scene':18s} " + "median seconds per stage", flush=True)
    totals = []
    with tempfile.TemporaryDirectory() as tmp:
        for scene in scenes:
            runs = [convert_scene(scene, Path(tmp)) for _ in range(args.repeats)]
            bad = [r.reason for r in runs if r.status != "ok"]
            if bad:
                print(f"{scene.scenario_id}: failed: {bad[0]}")
                continue
            stage_names = list(runs[0].timings)
            med = {s: statistics.median(r.timings[s] for r in runs) for s in stage_names}
            totals.append(med["total"])
            print(f"{scene.scenario_id:18s} " + "  ".join(f"{s}={med[s]:.3f}" for s in stage_names),
                  flush=True)
    if totals:
        print(f"median total per scene: {statistics.median(totals):.3f} s "
              f"(max {max(totals):.3f} s; goal <= 2 s)")
    return 0


def _rss_now_mib() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2 ** 20


def _peak_mib(who: int) -> float:
    return resource.getrusage(who).ru_maxrss / 1024  # KiB on Linux


def shard(args: argparse.Namespace) -> int:
    from converters.sumo import ConvertOptions
    from converters.sumo.batch import convert_files
    from converters.womd import write_womd

    base = load_scene(args.scene)
    n = args.shard
    marks = sorted({m for m in (50, 250, n) if m <= n} | {max(1, n * k // 10) for k in range(1, 10)})
    opts = ConvertOptions(baseline=not args.no_baseline)
    cores = min(args.workers, os.cpu_count() or 1)
    with tempfile.TemporaryDirectory(dir=args.tmp) as tmp:
        path = Path(tmp) / "shard.tfrecord"
        t0 = time.perf_counter()
        write_womd(path, (dataclasses.replace(base, scenario_id=f"{base.scenario_id}-{k:05d}")
                          for k in range(n)))
        print(f"shard: {n} copies of {base.scenario_id} ({path.stat().st_size / 2 ** 20:.1f} MiB) "
              f"written in {time.perf_counter() - t0:.1f} s; workers {args.workers}, "
              f"SUMO baseline run {'off' if args.no_baseline else 'on'}", flush=True)
        print(f"{'scenes':>6s} {'ok':>5s} {'failed':>6s} {'wall s':>8s} {'scenes/s/core':>13s} "
              f"{'parent peak MiB':>15s} {'parent now MiB':>14s} {'worker peak MiB':>15s}",
              flush=True)
        out = Path(tmp) / "out"
        done = ok = 0
        t0 = time.perf_counter()
        for row in convert_files([path], out, workers=args.workers, options=opts):
            done += 1
            ok += row.status == "ok"
            if row.status != "ok" and done - ok <= 3:
                print(f"  {row.status}: {row.reason}", flush=True)
            if done in marks:
                wall = time.perf_counter() - t0
                print(f"{done:6d} {ok:5d} {done - ok:6d} {wall:8.1f} {ok / wall / cores:13.3f} "
                      f"{_peak_mib(resource.RUSAGE_SELF):15.1f} {_rss_now_mib():14.1f} "
                      f"{_peak_mib(resource.RUSAGE_CHILDREN):15.1f}", flush=True)
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*", type=Path,
                    default=sorted((ROOT / "data" / "womd").glob("*.tfrecord")))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--shard", type=int, metavar="N",
                    help="convert a shard of N copies of --scene (throughput, memory)")
    ap.add_argument("--scene", type=Path, default=ROOT / "data" / "womd" / "850c48d8bbfa008f.tfrecord")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--no-baseline", action="store_true", help="skip the SUMO run per scene")
    ap.add_argument("--tmp", type=Path, help="folder for the shard and bundles (default: TMPDIR)")
    args = ap.parse_args()
    return shard(args) if args.shard else stages(args)


if __name__ == "__main__":
    sys.exit(main())
