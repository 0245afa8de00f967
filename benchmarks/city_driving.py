"""Learned drivers in whole cities against SUMO's default drivers: the figures of issue 32's goals.

Runs ``magail-sumo evaluate --city`` (:func:`magail_sumo.evaluation.city.evaluate_city`) for
each policy on each city (the same window, warm-up and seed for every method), then prints per
city and policy: trips completed against SUMO's drivers in the same window, vehicles taken out
for a collision or leaving the road and red-light runs as shares of the learned trips (agents
that drove in the window), mean travel time against SUMO's, the most agents alive at once,
the vehicles left SUMO-driven for a turn tighter than a car can make (``tight``,
``CityEnvConfig.agent_tight_turns``), the SUMO-driven vehicles released from giving way to
standing agents (``unblk``, ``CityEnvConfig.unblock_s``) and those moved on past a junction
where they and an agent stood in each other's path (``jump``), and with ``--humans EXPERT_DIR``
the Jensen-Shannon divergence of the agents' and of SUMO's drivers' speed and 1-s
acceleration distributions from the recorded humans'
(:mod:`magail_sumo.evaluation.city_kinematics`).

Usage (evaluate on cities the policies were not trained on)::

    python benchmarks/city_driving.py --policy runs/route_city/checkpoints/latest.pt \\
        --policy pretrained --city data/sumo/cologne8 --steps 6000 --warmup-s 600 \\
        --max-agents 200 --humans out/expert_womd14_route --out out/bench_city

Each policy writes ``OUT/<n>/city.json`` (n: its position in ``--policy``); the table is
printed from those rows, so ``--table-only`` reprints it without running anything.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from magail_sumo.evaluation.city import SUMO_METHOD, CitySettings, evaluate_city, read_rows


def _share(n: float, d: float) -> float:
    return n / d if d else float("nan")


def table(folders: list[Path]) -> list[str]:
    """The goal figures of every policy row of ``folders``' ``city.json``, as lines."""
    lines = [f"{'city':<14} {'policy':<34} {'trips':>6} {'sumo':>6} {'ratio':>6} "
             f"{'removed':>8} {'red':>6} {'tt_ratio':>8} {'peak':>5} {'agents':>6} {'tight':>5} "
             f"{'unblk':>5} {'jump':>4} "
             f"{'speedJS':>7} {'accJS':>6} {'sumo_speedJS':>12} {'sumo_accJS':>10}"]
    for folder in folders:
        rows, _ = read_rows(folder)
        sumo = {r["scenario"]: r for r in rows if r["method"] == SUMO_METHOD}
        for r in rows:
            if r["method"] == SUMO_METHOD or r["scenario"] not in sumo:
                continue
            s = sumo[r["scenario"]]
            ends = r["terminations"]
            out = ends.get("collision", 0) + ends.get("off_road", 0)
            lines.append(
                f"{r['scenario']:<14} {r['method'][:34]:<34} {r['arrived']:>6} {s['arrived']:>6} "
                f"{_share(r['arrived'], s['arrived']):>6.2f} "
                f"{_share(out, r['agents']):>8.1%} {_share(ends.get('red_light', 0), r['agents']):>6.1%} "
                f"{_share(r['travel_time_s'], s['travel_time_s']):>8.2f} "
                f"{r.get('peak_agents', math.nan):>5.0f} {r['agents']:>6} "
                f"{r.get('tight_turns', math.nan):>5.0f} "
                f"{r.get('unblocked', math.nan):>5.0f} "
                f"{r.get('jumped', math.nan):>4.0f} "
                f"{r.get('speed_js_humans', math.nan):>7.3f} "
                f"{r.get('accel_js_humans', math.nan):>6.3f} "
                f"{s.get('speed_js_humans', math.nan):>12.3f} "
                f"{s.get('accel_js_humans', math.nan):>10.3f}")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--policy", action="append", required=True,
                    help="policy spec (checkpoint, pretrained[:NAME], ...); repeatable")
    ap.add_argument("--city", action="append", default=[],
                    help="city scenario (.sumocfg or its folder); repeatable")
    ap.add_argument("--steps", type=int, default=6000, help="0.1-s steps of the window")
    ap.add_argument("--warmup-s", type=float, default=600.0)
    ap.add_argument("--max-agents", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--humans", help="expert data of recorded humans (the JS columns)")
    ap.add_argument("--unblock-s", type=float, default=CitySettings.unblock_s,
                    help="CityEnvConfig.unblock_s (0: no release of blocked junctions)")
    ap.add_argument("--demand-scale", type=float, default=1.0,
                    help="each city's demand times this in both runs (SUMO's --scale)")
    ap.add_argument("--deterministic", action="store_true",
                    help="a checkpoint policy acts with its mean action (default: it samples)")
    ap.add_argument("--noise-scale", type=float, default=None,
                    help="a sampling policy's noise scale (default: the policy's own)")
    ap.add_argument("--out", default="out/bench_city")
    ap.add_argument("--table-only", action="store_true", help="print the table of OUT only")
    args = ap.parse_args()
    out = Path(args.out)
    folders = [out / str(i) for i in range(len(args.policy))]
    if not args.table_only:
        st = CitySettings(steps=args.steps, warmup_s=args.warmup_s, max_agents=args.max_agents,
                          seed=args.seed, timeout_s=None, humans=args.humans,
                          unblock_s=args.unblock_s, deterministic=args.deterministic,
                          noise_scale=args.noise_scale, demand_scale=args.demand_scale)
        for spec, folder in zip(args.policy, folders):
            res = evaluate_city(spec, args.city, folder, st)
            for e in res.errors:
                print("error:", e)
    acting = (", mean actions" if args.deterministic else "") + \
        ("" if args.noise_scale is None else f", noise scale {args.noise_scale:g}")
    dense = f", demand ×{args.demand_scale:g}" if args.demand_scale != 1.0 else ""
    print(f"window {args.steps / 10:g} s after a {args.warmup_s:g} s warm-up{dense}, at most "
          f"{args.max_agents} agents, seed {args.seed}{acting}; trips: completed in the window; "
          "removed:"
          " collision + off-road per learned trip; red: red-light runs per learned trip; "
          "tt_ratio: mean travel time / SUMO's; JS: bits from the recorded humans "
          "(sumo_*: SUMO's drivers in SUMO's own run of the window)")
    print("\n".join(table(folders)))


if __name__ == "__main__":
    main()
