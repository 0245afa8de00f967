"""Memory over a scene pool: trainer and scene-worker RSS while every scene of a large pool plays.

A pool of ``--scenes`` distinct scene files (default 1,000) is built in a temporary folder as
symlinks ``s0000_<name>.pkl``, ``s0001_<name>.pkl``, … cycling over the real WOMD ScenarioNet
pickles of ``data/scenarionet/`` (the nuScenes one left out), listed with ``resolve_pool`` and
played by ``pool_vec_env`` over ``--workers`` workers of ``--backend`` (``process``: one
process each, the default; ``hosted``: shared out over one process per core) (seed 0; ``--cache`` scene envs
kept per worker, default ``SCENE_CACHE`` as in training; bundles converted on demand into the
temporary folder: one per scenario id, so the 11 real scenes are converted once and every other
file reuses its bundle, but each file is its own pool record, read and given its own env when
it plays). Env: ``EnvConfig(start_window="random",
max_steps=--max-steps (8), controlled=4)``, short episodes so that many fit. Uniform random
actions (seeded) are stepped until ``venv.episodes >= scenes``: each worker plays its shard in a
seeded permutation, so by then about every record of the pool has been played once.

A row is printed right after the first reset and when 10 %, 25 %, 50 % and 100 % of the
``scenes`` episodes are done: ``episodes`` (finished), ``positions`` (distinct pool records whose
episode finished, from each worker's seeded order), ``trainer_rss_mib`` / ``trainer_peak_mib``
(``VmRSS`` / ``VmHWM`` of this process, from ``/proc/<pid>/status``), ``worker_rss_mib`` /
``worker_peak_mib`` (the same, one per worker process — a hosted process once; libsumo runs
inside the worker),
``worker_rss_sum_mib`` and ``seconds`` since the env was made (start-up excluded:
``startup_s`` in the first row). A last line (``summary`` row with ``--json``) gives the growth
of the summed worker RSS from the 10 % row to the end, in MiB and %.

    python benchmarks/pool_memory.py [--json] [--scenes N] [--workers W] [--max-steps S]
        [--cache C] [--backend process|hosted]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SCENARIONET = ROOT / "data" / "scenarionet"
FRACTIONS = (0.10, 0.25, 0.50, 1.00)


def proc_mem(pid: int) -> tuple[float | None, float | None]:
    """(VmRSS, VmHWM) of process ``pid`` in MiB, from ``/proc/<pid>/status`` (None: gone)."""
    rss = hwm = None
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    rss = int(line.split()[1]) / 1024.0
                elif line.startswith("VmHWM:"):
                    hwm = int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return rss, hwm


def build_pool(folder: Path, n: int) -> list[Path]:
    """``n`` distinct symlinks cycling over the real WOMD ScenarioNet pickles."""
    sources = sorted(p for p in SCENARIONET.glob("*.pkl")
                     if not p.name.startswith("sd_nuscenes_")
                     and p.name != "dataset_summary.pkl" and p.name != "dataset_mapping.pkl")
    if not sources:
        raise SystemExit(f"no ScenarioNet pickle in {SCENARIONET}")
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(n):
        src = sources[i % len(sources)]
        link = folder / f"s{i:04d}_{src.name}"
        link.symlink_to(src.resolve())
        out.append(link)
    return out


def positions_played(venv, n_refs: int) -> int:
    """Distinct pool records (global positions) whose episode has finished, from each
    worker's seeded order (records that failed are not accounted for: none in this pool)."""
    from magail_sumo.env.scene_pool import PoolCursor

    workers = len(venv.specs)
    seen: set[int] = set()
    for k, spec in enumerate(venv.specs):
        cur = PoolCursor(spec.refs, spec.networks, venv.seed_base + _stride() * k,
                         make_env=None, config=venv.config)
        n = len(spec.refs)
        orders: dict[int, np.ndarray] = {}
        for e in range(int(venv._episode[k])):  # episodes 0 .. current - 1 are finished
            if e // n not in orders:
                orders[e // n] = cur.order(e // n)
            seen.add(k + workers * int(orders[e // n][e % n]))
    return len([p for p in seen if p < n_refs])


def _stride() -> int:
    from magail_sumo.env.vec_env import SEED_STRIDE

    return SEED_STRIDE


def snapshot(venv, label: str, n_refs: int, t0: float) -> dict:
    t_rss, t_hwm = proc_mem(os.getpid())
    w_rss, w_hwm = [], []
    for pid in dict.fromkeys(h.pid for h in venv._handles):  # a process once (hosted backend)
        r, p = proc_mem(pid)
        w_rss.append(None if r is None else round(r, 1))
        w_hwm.append(None if p is None else round(p, 1))
    return {"checkpoint": label, "scenes": n_refs, "workers": len(venv.specs),
            "episodes": int(venv.episodes), "positions": positions_played(venv, n_refs),
            "trainer_rss_mib": round(t_rss, 1), "trainer_peak_mib": round(t_hwm, 1),
            "worker_rss_mib": w_rss, "worker_peak_mib": w_hwm,
            "worker_rss_sum_mib": round(sum(r for r in w_rss if r is not None), 1),
            "restarts": int(venv.restarts), "skipped": len(venv.skipped),
            "seconds": round(time.perf_counter() - t0, 1)}


def show(row: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(row), flush=True)
        return
    w = " ".join(f"{r}/{p}" for r, p in zip(row["worker_rss_mib"], row["worker_peak_mib"]))
    print(f"{row['checkpoint']:>6}  episodes {row['episodes']:5d}  positions "
          f"{row['positions']:5d}/{row['scenes']}  trainer rss/peak {row['trainer_rss_mib']}/"
          f"{row['trainer_peak_mib']} MiB  workers rss/peak {w} MiB  (sum "
          f"{row['worker_rss_sum_mib']})  {row['seconds']} s", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="one JSON object per row")
    ap.add_argument("--scenes", type=int, default=1000, help="pool size (records)")
    ap.add_argument("--workers", type=int, default=2, help="scene workers")
    ap.add_argument("--max-steps", type=int, default=8, help="env steps per episode")
    ap.add_argument("--controlled", type=int, default=4, help="controlled agents per scene")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--backend", default="process",
                    help="worker backend: process (one process per worker) or hosted (the "
                         "workers shared out over one process per core)")
    ap.add_argument("--cache", type=int, default=None,
                    help="scene envs each worker keeps (default: workers.scene_cache's default)")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")

    from magail_sumo.env.config import SCENE_CACHE, EnvConfig
    from magail_sumo.env.scene_pool import resolve_pool
    from magail_sumo.env.vec_env import pool_vec_env

    cfg = EnvConfig(start_window="random", max_steps=args.max_steps, controlled=args.controlled)
    logs: list[str] = []
    with tempfile.TemporaryDirectory(prefix="pool_memory_") as tmp:
        tmp = Path(tmp)
        build_pool(tmp / "pool", args.scenes)
        refs = resolve_pool([str(tmp / "pool")])
        n = len(refs)
        ts = time.perf_counter()
        venv = pool_vec_env(refs, tmp / "networks", args.workers, cfg, seed=args.seed,
                            cache=SCENE_CACHE if args.cache is None else args.cache,
                            convert_budget_s=90, log=logs.append, backend=args.backend)
        rows = []
        try:
            rng = np.random.default_rng(args.seed)
            venv.reset()
            t0 = time.perf_counter()
            row = snapshot(venv, "reset", n, t0)
            row["startup_s"] = round(t0 - ts, 1)
            rows.append(row)
            show(row, args.json)
            targets = [(f"{int(f * 100)}%", max(1, math.ceil(f * n))) for f in FRACTIONS]
            steps = 0
            while targets:
                venv.step(rng.uniform(-1, 1, (venv.num_envs, 2)).astype(np.float32))
                steps += 1
                while targets and venv.episodes >= targets[0][1]:
                    row = snapshot(venv, targets.pop(0)[0], n, t0)
                    row["steps"] = steps
                    rows.append(row)
                    show(row, args.json)
        finally:
            venv.close()
        for line in logs:
            print(f"# {line}", file=sys.stderr)
    first = next(r for r in rows if r["checkpoint"] == "10%")
    last = rows[-1]
    growth = last["worker_rss_sum_mib"] - first["worker_rss_sum_mib"]
    pct = 100.0 * growth / first["worker_rss_sum_mib"] if first["worker_rss_sum_mib"] else 0.0
    summary = {"summary": "worker_rss_growth_10pct_to_end", "scenes": n,
               "episodes": last["episodes"], "from_mib": first["worker_rss_sum_mib"],
               "to_mib": last["worker_rss_sum_mib"], "growth_mib": round(growth, 1),
               "growth_pct": round(pct, 1),
               "trainer_growth_mib": round(last["trainer_rss_mib"] - first["trainer_rss_mib"], 1),
               "trainer_peak_mib": last["trainer_peak_mib"],
               "worker_peak_mib": last["worker_peak_mib"], "seconds": last["seconds"]}
    if args.json:
        print(json.dumps(summary), flush=True)
    else:
        print(f"worker RSS (sum) {first['worker_rss_sum_mib']} MiB at 10% -> "
              f"{last['worker_rss_sum_mib']} MiB at the end: {growth:+.1f} MiB ({pct:+.1f}%); "
              f"trainer {last['trainer_rss_mib'] - first['trainer_rss_mib']:+.1f} MiB; peaks: "
              f"trainer {last['trainer_peak_mib']} MiB, workers {last['worker_peak_mib']} MiB",
              flush=True)


if __name__ == "__main__":
    main()
