"""``magail-sumo convert``: recorded scenes -> SUMO scenarios (thin layer over converters.sumo)."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from magail_sumo.cli.argtypes import timeout_s
from magail_sumo.cli.progress import progress
from magail_sumo.outputs import OutputError, printable, safe_name


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("convert", help="convert recorded scenes into SUMO scenarios",
                       description="Write DIR/<scenario_id>/ (net, routes, signal programs, "
                                   ".sumocfg, conversion.json) for every scene of the inputs, "
                                   "and DIR/summary.csv. DIR must be new, empty or written by "
                                   "magail-sumo; an id that is not a plain file name is stored "
                                   "under a safe name (its safe characters plus a hash).")
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="WOMD TFRecord files/shards or ScenarioNet pickles/dataset folders")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    p.add_argument("--workers", type=int, default=1, metavar="N", help="parallel processes")
    p.add_argument("--skip-bad", action="store_true",
                   help="go on past unreadable records and failed scenes (exit 0 if any converts)")
    p.add_argument("--cycle-signals", action="store_true",
                   help="repeat the recorded signal states past the end of the log")
    p.add_argument("--no-baseline", action="store_true",
                   help="skip the SUMO run (no signal_fidelity / sumo_baseline)")
    p.add_argument("--opendrive", action="store_true",
                   help="also write DIR/<scenario_id>/<scenario_id>.xodr (OpenDRIVE, through "
                        "netconvert)")
    p.add_argument("--pedestrians", action="store_true",
                   help="sidewalks on road edges and crossings at the crosswalks, so recorded "
                        "pedestrians walk in SUMO as persons and SUMO's drivers yield to them "
                        "(conversion.json 'pedestrians': crossings built, crosswalks dropped)")
    p.add_argument("--force", action="store_true",
                   help="reconvert scenes whose bundle in DIR was already converted by this "
                        "converter version with the same options (default: skip them)")
    p.add_argument("--timeout-s", type=timeout_s, default=600.0, metavar="S",
                   help="seconds one scene may take before it is reported failed (its worker "
                        "is killed with --workers > 1; default 600; 'none': no limit)")
    p.set_defaults(func=run)


def _fmt(value: object, spec: str = ".3f") -> str:
    return "n/a" if value is None else format(value, spec)


def format_quality(scenario_id: str, q: dict, folder: Path) -> str:
    """The quality report of one converted scene, as printed by the command."""
    # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
    from converters.sumo.quality import BARS, failed_bars

    base = q.get("sumo_baseline") or {}
    failed = failed_bars(q)
    return "\n".join([
        f"{scenario_id}: converted -> {folder}",
        f"  on_network_rate     {_fmt(q.get('on_network_rate'))}   "
        f"(bar >= {BARS['on_network_rate']:g}; map lanes only: "
        f"{_fmt(q.get('on_network_rate_map_only'))}, synthesised lanes: {q.get('synthesized_lanes', 0)})",
        f"  route_rate          {_fmt(q.get('route_rate'))}   (bar >= {BARS['route_rate']:g})",
        f"  signal_fidelity     {_fmt(q.get('signal_fidelity'))}   "
        f"(bar >= {BARS['signal_fidelity']:g}; n/a without signals)",
        f"  bars                {'all met' if not failed else 'below: ' + ', '.join(failed)}",
        *([f"  off the network     {_off(q['off_network'])}"]
          if "on_network_rate" in failed and q.get("off_network") else []),
        *([f"  route misses        {_misses(q['route_misses'], 'track')}"]
          if q.get("route_misses") else []),
        *([f"  signal misses       {_misses(q['signal_misses'], 'lane')}"]
          if q.get("signal_misses") else []),
        f"  netconvert_warnings {q.get('netconvert_warnings')}"
        + (f" (text: {folder / 'netconvert-warnings.txt'})" if q.get("netconvert_warnings")
           else ""),
        f"  SUMO baseline       ADE {_fmt(base.get('ade'), '.2f')} m, FDE {_fmt(base.get('fde'), '.2f')} m, "
        f"{base.get('collisions')} collisions, {base.get('teleports')} teleports"
        + (f", {base['parked_overlaps']} overlapping parked vehicles"
           if base.get("parked_overlaps") is not None else ""),
    ])


def _misses(misses: list, key: str, shown: int = 3) -> str:
    """What is behind a figure below 1 (vehicles by ``key`` "track", signalled lanes by
    "lane"), for the quality report: a count, the first few."""
    first = "; ".join(f"{key} {m.get(key)}: {m.get('reason')}" for m in misses[:shown])
    more = f"; ... ({len(misses)} in conversion.json)" if len(misses) > shown else ""
    return f"{len(misses)}: {first}{more}"


def _off(off: list, shown: int = 3) -> str:
    """The vehicles behind a low on-network rate, for the quality report."""
    first = "; ".join(f"track {m.get('track')}: {m.get('off')} of {m.get('of')} states off "
                      "every lane" for m in off[:shown])
    more = f"; ... ({len(off)} in conversion.json)" if len(off) > shown else ""
    return f"{len(off)}: {first}{more}"


def _line(text: str) -> str:
    """``text`` as one line (control characters escaped only where there are any)."""
    return text if text.isprintable() else printable(text, 2000)


def run(args: argparse.Namespace) -> int:
    # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
    from converters.sumo.batch import convert_files, write_summary
    from converters.sumo.scenario import ConvertOptions, claim_networks_dir

    # a new, empty or magail_sumo folder only (see claim_networks_dir); bundles go to
    # OUT/<safe name of the scenario id>/, never outside OUT
    claim_networks_dir(args.out, ["summary.csv"])
    opts = ConvertOptions(cycle_signals=args.cycle_signals, baseline=not args.no_baseline,
                          time_budget_s=args.timeout_s, opendrive=args.opendrive,
                          pedestrians=args.pedestrians)
    rows = []
    workers = max(args.workers, 1)
    clock = time.perf_counter()
    for row in progress(convert_files(args.inputs, args.out, workers, opts, force=args.force),
                        desc="scenes", unit="scene"):
        rows.append(row)
        if row.status == "ok":
            print(format_quality(printable(row.scenario_id), row.quality,
                                 args.out / safe_name(row.scenario_id)), flush=True)
        elif row.status == "skipped":
            print(f"skipped: {_line(row.reason)}", flush=True)
        else:
            print(f"error: {_line(row.reason)}", file=sys.stderr, flush=True)
            if not args.skip_bad:
                break
    try:
        write_summary(args.out / "summary.csv", rows)
        claim_networks_dir(args.out, ["summary.csv", *(
            safe_name(r.scenario_id) for r in rows
            if r.status != "unreadable" and (args.out / safe_name(r.scenario_id)).is_dir())])
    except OSError as exc:
        raise OutputError(f"{args.out / 'summary.csv'}: cannot write "
                          f"({exc.strerror or type(exc).__name__})") from None
    wall = time.perf_counter() - clock
    ok = sum(r.status == "ok" for r in rows)
    skipped = sum(r.status == "skipped" for r in rows)
    bad = len(rows) - ok - skipped
    cores = min(workers, os.cpu_count() or 1)
    rate = f"{ok / wall / cores:.3f}" if ok and wall > 0 else "n/a"
    print(f"converted {ok} scene(s), {skipped} skipped (already converted), {bad} failed or "
          f"unreadable in {wall:.1f} s: {rate} scenes/s per core ({cores} core(s)); summary: "
          f"{args.out / 'summary.csv'}", file=sys.stderr)
    if bad and not args.skip_bad:
        return 1
    return 0 if ok or skipped else 1
