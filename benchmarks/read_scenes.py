"""Benchmark: reading real WOMD scenes (scenes/s, MB/s) and peak memory on a large shard.

Reads the bundled real scenes ``--repeats`` times (median over repeats), then builds one large
synthetic shard by concatenating their records ``--copies`` times and reads it in a child
process, comparing that process's peak RSS with a child that reads a single scene: memory must
stay flat (bounded by one scene), not grow with the shard.

    python benchmarks/read_scenes.py [--repeats 15] [--copies 100] [--json]
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from converters import iter_scenes  # noqa: E402
from converters.tfrecord import iter_records, write_records  # noqa: E402

SCENES = sorted((ROOT / "data" / "womd").glob("*.tfrecord"))

_CHILD = """
import resource, sys, time
sys.path.insert(0, {root!r})
from converters import iter_scenes
t = time.perf_counter(); n = 0
for scene in iter_scenes({path!r}):
    n += 1
dt = time.perf_counter() - t
print(n, dt, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def child_read(path: Path) -> tuple[int, float, float]:
    """(scenes, seconds, peak RSS MiB) of a fresh process reading ``path``."""
    out = subprocess.run([sys.executable, "-c", _CHILD.format(root=str(ROOT), path=str(path))],
                         capture_output=True, text=True, check=True)
    n, dt, rss_kib = out.stdout.split()
    return int(n), float(dt), int(rss_kib) / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--copies", type=int, default=100, help="copies of the real scenes in the big shard")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    total_mb = sum(p.stat().st_size for p in SCENES) / 1e6
    for _ in iter_scenes(SCENES):  # warm-up: imports, page cache
        pass
    per_file: dict[str, list[float]] = {p.stem: [] for p in SCENES}
    rounds = []
    for _ in range(args.repeats):
        t_all = time.perf_counter()
        for p in SCENES:
            t = time.perf_counter()
            for _scene in iter_scenes(p):
                pass
            per_file[p.stem].append(time.perf_counter() - t)
        rounds.append(time.perf_counter() - t_all)
    med = statistics.median(rounds)
    result = {
        "scenes_per_s": len(SCENES) / med,
        "mb_per_s": total_mb / med,
        "ms_per_scene": {k: 1e3 * statistics.median(v) for k, v in per_file.items()},
        "repeats": args.repeats,
    }

    with tempfile.TemporaryDirectory() as tmp:
        datas = [d for p in SCENES for _, d in iter_records(p)]
        big = Path(tmp) / "big.tfrecord"
        write_records(big, (d for _ in range(args.copies) for d in datas))
        n_one, _, rss_one = child_read(SCENES[0])
        n_big, dt_big, rss_big = child_read(big)
        result.update({
            "big_shard_scenes": n_big,
            "big_shard_mb": big.stat().st_size / 1e6,
            "big_shard_scenes_per_s": n_big / dt_big,
            "peak_rss_mib_one_scene": rss_one,
            "peak_rss_mib_big_shard": rss_big,
        })
    result["process_peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if args.json:
        print(json.dumps(result))
        return
    print(f"real scenes ({len(SCENES)} files, {total_mb:.2f} MB), median of {args.repeats} rounds:")
    print(f"  {result['scenes_per_s']:.1f} scenes/s, {result['mb_per_s']:.1f} MB/s (one core)")
    for k, v in result["ms_per_scene"].items():
        print(f"  {k}: {v:.1f} ms")
    print(f"large shard: {n_big} scenes, {result['big_shard_mb']:.0f} MB, "
          f"{result['big_shard_scenes_per_s']:.1f} scenes/s")
    print(f"  peak RSS reading one scene {rss_one:.0f} MiB vs the whole shard {rss_big:.0f} MiB")


if __name__ == "__main__":
    main()
