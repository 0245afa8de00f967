"""Every converted scene against the converter's bars, with the named causes of each miss.

    python benchmarks/conversion_bars.py NETWORKS_DIR [--against OLD_DIR] [--markdown]

Reads ``NETWORKS_DIR/summary.csv`` and each bundle's ``conversion.json`` (``magail-sumo convert
... --out NETWORKS_DIR``) and prints one row per scene: its source folder, status, the bar
figures (on-network >= 0.98, route rate >= 0.95, signal fidelity >= 0.99 where signals
exist), the bars it misses, and the causes the conversion names for them (route misses by
cause, signalled lanes by cause); then per source folder the scenes meeting every bar and the
median route rate. ``--against`` prints the same summary for a folder converted by another
converter, for a before/after in one run.
"""

from __future__ import annotations

import argparse
import collections
import csv
import json
import re
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from converters.sumo.quality import failed_bars  # noqa: E402


def _cause(reason: str) -> str:
    """A miss's reason without its numbers (for counting causes)."""
    if reason.startswith("covers"):
        m = re.search(r"off the network at ([\d.]+), reversing at ([\d.]+), on other lanes at "
                      r"([\d.]+)", reason)
        if m:
            parts = dict(zip(("off the network", "reversing", "on other lanes"),
                             map(float, m.groups())))
            return "leaves its route: mostly " + max(parts, key=parts.get)
        return "leaves its route"
    return re.sub(r"[\d.]+", "N", reason)


def rows(folder: Path) -> list[dict]:
    out = []
    for r in csv.DictReader(open(folder / "summary.csv")):
        conv = folder / r["scenario_id"] / "conversion.json"
        q = json.loads(conv.read_text()).get("quality", {}) if conv.is_file() else {}
        src = Path(r["file"]).parent.name
        causes = collections.Counter(_cause(m["reason"]) for m in q.get("route_misses", []))
        causes.update(f"signal: {_cause(m['reason'])}" for m in q.get("signal_misses", []))
        if "on_network_rate" in failed_bars(q):
            causes.update("states off every lane" for m in q.get("off_network", []))
        out.append({"scene": r["scenario_id"], "source": src, "status": r["status"],
                    "on": q.get("on_network_rate"), "route": q.get("route_rate"),
                    "signal": q.get("signal_fidelity"),
                    "failed": failed_bars(q) if r["status"] == "ok" else ["not converted"],
                    "causes": causes, "reason": r["reason"]})
    return out


def _f(v) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def summary(label: str, table: list[dict]) -> None:
    by = collections.defaultdict(list)
    for r in table:
        by[r["source"]].append(r)
    print(f"\n{label}: source | scenes | converted | meet every bar | median route rate")
    for src, rs in sorted(by.items()):
        routes = [r["route"] for r in rs if r["route"] is not None]
        print(f"{src} | {len(rs)} | {sum(r['status'] == 'ok' for r in rs)} | "
              f"{sum(not r['failed'] for r in rs)} | "
              f"{statistics.median(routes):.3f}" if routes else "n/a")
    print(f"all | {len(table)} | {sum(r['status'] == 'ok' for r in table)} | "
          f"{sum(not r['failed'] for r in table)} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--against", type=Path, default=None)
    args = ap.parse_args()
    table = rows(args.folder)
    print("scene | source | on-network | route rate | signal fidelity | bars missed | "
          "named causes")
    for r in table:
        causes = "; ".join(f"{k} x{v}" for k, v in r["causes"].most_common()) or r["reason"]
        print(f"{r['scene']} | {r['source']} | {_f(r['on'])} | {_f(r['route'])} | "
              f"{_f(r['signal'])} | {', '.join(r['failed']) or 'none'} | {causes}")
    summary(str(args.folder), table)
    if args.against:
        summary(str(args.against), rows(args.against))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
