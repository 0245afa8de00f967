"""SUMO's drivers against the recorded non-moving vehicles, in plain ``sumo -c`` runs of bundles.

    python benchmarks/parked_collisions.py NETWORKS_DIR [NETWORKS_DIR ...] [--scenes ID ...]

For every converted bundle in each networks folder (``magail-sumo convert --out``), runs its
``.sumocfg`` as ``sumo -c`` does (:func:`converters.sumo.baseline.run_baseline`, the converter's
quality run) and prints per scene: the non-moving vehicles of the recording (moved less than
``PARKED_MOVE`` m), how many of them the bundle's SUMO files carry (vehicles with a stop), the
SUMO-driven vehicles whose box overlaps a recorded non-moving vehicle's box at some step
(``parked_overlaps``), and SUMO's own collision and teleport counts. Give two folders converted
by two converters (the same scenes) to compare them in one run; the totals come last.
"""

from __future__ import annotations

import argparse
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from converters import load_scene  # noqa: E402
from converters.sumo.baseline import parked_boxes, run_baseline  # noqa: E402
from converters.sumo.bundle import BundleLayout, read_report  # noqa: E402


def measure(folder: Path) -> dict | None:
    """The figures of one bundle folder (None when it did not convert or lost its source)."""
    rep = read_report(folder)
    src = rep.get("source") or {}
    if rep.get("status") != "ok" or not src.get("file"):
        return None
    scene = load_scene(src["file"], src.get("record") or 0)
    files = BundleLayout.of(folder, scene.scenario_id)
    root = ET.parse(files.routes).getroot()
    carried = sum(v.find("stop") is not None for v in root.iter("vehicle"))
    base = run_baseline(scene, str(files.sumocfg), [], None)
    return {"scene": scene.scenario_id, "parked": len(parked_boxes(scene)[0]),
            "in_sumo": carried, "overlaps": base.parked_overlaps or 0,
            "collisions": base.collisions, "teleports": base.teleports}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dirs", nargs="+", type=Path, help="networks folders (convert --out)")
    ap.add_argument("--scenes", nargs="*", default=None, help="only these scenario ids")
    args = ap.parse_args()
    names = sorted({p.name for d in args.dirs for p in d.iterdir()
                    if (p / "conversion.json").is_file()})
    if args.scenes:
        names = [n for n in names if any(n.startswith(s) or s in n for s in args.scenes)]
    totals = {d: dict.fromkeys(("parked", "in_sumo", "overlaps", "collisions", "teleports"), 0)
              for d in args.dirs}
    print("scene | folder | non-moving | in SUMO files | SUMO drivers overlapping them | "
          "SUMO collisions | teleports", flush=True)
    for name in names:
        for d in args.dirs:
            if not (d / name / "conversion.json").is_file():
                continue
            m = measure(d / name)
            if m is None:
                print(f"{name} | {d} | not converted", flush=True)
                continue
            for k in totals[d]:
                totals[d][k] += m[k]
            print(f"{m['scene']} | {d} | {m['parked']} | {m['in_sumo']} | {m['overlaps']} | "
                  f"{m['collisions']} | {m['teleports']}", flush=True)
    for d, t in totals.items():
        print(f"TOTAL | {d} | {t['parked']} | {t['in_sumo']} | {t['overlaps']} | "
              f"{t['collisions']} | {t['teleports']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
