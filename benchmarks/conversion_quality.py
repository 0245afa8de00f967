"""Route rate, on-network rate and junction size of converted real scenes (issue 14, item 4).

    python benchmarks/conversion_quality.py [--out DIR] [--no-baseline] [FILE...]

Converts the scenes (default: ``data/womd/*.tfrecord``, ``data/scenarionet/*.pkl`` and, where
present, ``$MAGAIL_SUMO_SHARED_DATA/scenarionet/nuscenes/*.pkl``, default
``../shared/data``) with ``magail-sumo convert`` into DIR (default a temporary folder), then
prints one row per scene: ``route_rate``, ``on_network_rate``, the largest junction diameter
(m: the largest distance between two planned lane ends that meet at one node, read from the
bundle's ``.edg.xml``), netconvert warnings, the SUMO baseline's ADE / collisions / teleports,
and whether ``sumo -c`` loads and runs the bundle without an error; then the scenes below the
0.95 route-rate bar.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BAR = 0.95


def junction_diameter(edg: Path) -> tuple[float, str]:
    """(largest distance in m between two lane ends meeting at one node, that node's id)."""
    ends: dict[str, list] = {}
    for e in ET.parse(edg).getroot().iter("edge"):
        for lane in e.iter("lane"):
            pts = [[float(v) for v in p.split(",")[:2]] for p in lane.get("shape").split()]
            ends.setdefault(e.get("from"), []).append(pts[0])
            ends.setdefault(e.get("to"), []).append(pts[-1])
    best = (0.0, "")
    for node, pts in ends.items():
        p = np.asarray(pts)
        best = max(best, (float(np.sqrt(((p[:, None] - p[None]) ** 2).sum(-1)).max()), node))
    return best


def sumo_loads(bundle: Path) -> bool:
    """``sumo -c`` runs the bundle to its end with exit status 0 and no error."""
    cfg = next(bundle.glob("*.sumocfg"))
    out = subprocess.run([shutil.which("sumo") or "sumo", "-c", cfg.name, "--no-step-log", "true"],
                         cwd=bundle, capture_output=True, text=True, timeout=300)
    return out.returncode == 0 and "Error" not in out.stderr


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*", type=Path)
    ap.add_argument("--out", type=Path, help="output folder (default: a temporary one)")
    ap.add_argument("--no-baseline", action="store_true", help="skip the SUMO baseline run")
    args = ap.parse_args(argv)
    files = args.files
    if not files:
        shared = Path(os.environ.get("MAGAIL_SUMO_SHARED_DATA", ROOT.parent / "shared" / "data"))
        files = sorted((ROOT / "data" / "womd").glob("*.tfrecord")) + \
            sorted((ROOT / "data" / "scenarionet").glob("*.pkl")) + \
            sorted((shared / "scenarionet" / "nuscenes").glob("*.pkl"))
    out = args.out or Path(tempfile.mkdtemp(prefix="conversion_quality."))
    cmd = [sys.executable, "-m", "magail_sumo.cli.main", "convert", *map(str, files),
           "--out", str(out), "--skip-bad", "--force"] + (["--no-baseline"] if args.no_baseline else [])
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, env={**os.environ, "PYTHONPATH": str(ROOT)})
    print(f"{len(files)} files -> {out}")
    print(f"{'scene':34s} {'route':>6s} {'on_net':>6s} {'junction m':>10s} {'warn':>4s} "
          f"{'ADE m':>6s} {'coll':>4s} {'tp':>3s} sumo")
    below = []
    for bundle in sorted(p for p in out.iterdir() if (p / "conversion.json").is_file()):
        rep = json.loads((bundle / "conversion.json").read_text())
        q = rep["quality"]
        if rep["status"] != "ok":
            print(f"{rep['scenario_id'][:34]:34s} failed: {rep['reason']}")
            continue
        diam, node = junction_diameter(next(bundle.glob("*.edg.xml")))
        base = q.get("sumo_baseline") or {}
        ade = base.get("ade")
        print(f"{rep['scenario_id'][:34]:34s} {q['route_rate']:6.3f} {q['on_network_rate']:6.3f} "
              f"{diam:6.1f} {node:>3s} {q['netconvert_warnings']:4d} "
              f"{'-' if ade is None else f'{ade:.2f}':>6s} {base.get('collisions', '-')!s:>4s} "
              f"{base.get('teleports', '-')!s:>3s} {'ok' if sumo_loads(bundle) else 'FAILED'}")
        if q["route_rate"] is not None and q["route_rate"] < BAR:
            below.append(f"{rep['scenario_id']} {q['route_rate']:.3f}")
    print(f"below route_rate {BAR}: " + (", ".join(below) or "none"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
