"""Junction polygons and road fragments of converted networks: wedges and isolated edges.

    python benchmarks/junction_shapes.py NETWORKS_DIR [NETWORKS_DIR ...] [--wedge 15]

For every bundle's network in each folder (``magail-sumo convert --out``), counts the junctions
(nodes with internal lanes), the *wedges* -- junction polygons with a corner more than
``--wedge`` m from every lane point of the junction (its internal lanes, sampled every 0.5 m,
and the shapes of the lanes entering and leaving it): a spike netconvert draws towards an edge
end far from the junction -- and the *isolated fragments*: normal edges that no connection
enters or leaves (a piece of road SUMO's drivers can neither reach nor leave), and the lane
ends more than 1 m outside their junction's polygon (a gap sumo-gui shows as a hole between
road and junction) and the junction polygons that cross themselves (drawn as a ragged star
with holes). Per source folder and in total; several folders (several converters)
compare in one run.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from converters.sumo.geometry import point_segment, segments_cross  # noqa: E402
from converters.sumo.junction_shapes import GAP_M  # noqa: E402


def _dense(shape: np.ndarray, step: float = 0.5) -> np.ndarray:
    parts = [shape[:1]]
    for a, b in zip(shape[:-1], shape[1:]):
        n = max(2, int(np.hypot(*(b - a)) / step))
        parts.append(a + (b - a) * np.linspace(0, 1, n)[1:, None])
    return np.concatenate(parts)


def outside_distance(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(P,) distance (m) of each point to the closed ``polygon`` (Q, 2); 0 inside it (even-odd
    rule; a degenerate polygon, e.g. a line, has no inside)."""
    pts = np.asarray(points, np.float64)[:, :2]
    a = np.asarray(polygon, np.float64)[:, :2]
    b = np.roll(a, -1, axis=0)
    ab = b - a
    d = point_segment(pts, a, b)[0].min(1)
    # even-odd ray cast towards +x
    y, x = pts[:, 1:2], pts[:, 0:1]
    crosses = (a[None, :, 1] > y) != (b[None, :, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xc = a[None, :, 0] + (y - a[None, :, 1]) * ab[None, :, 0] / ab[None, :, 1]
    inside = ((crosses & (x < xc)).sum(1) % 2) == 1
    return np.where(inside, 0.0, d)


def self_intersecting(polygon: np.ndarray) -> bool:
    """Whether two non-neighbouring sides of the closed ``polygon`` (Q, 2) cross (a proper
    crossing; touching corners do not count)."""
    p = np.asarray(polygon, np.float64)[:, :2]
    if len(p) > 1 and abs(p[0, 0] - p[-1, 0]) + abs(p[0, 1] - p[-1, 1]) < 1e-6:
        p = p[:-1]
    n = len(p)
    if n < 4:
        return False
    k = np.arange(n)
    apart = np.abs(k[:, None] - k[None])
    cross = segments_cross(p, np.roll(p, -1, axis=0), p, np.roll(p, -1, axis=0))
    return bool((cross & (apart > 1) & (apart < n - 1)).any())


def measure(net_file: Path, wedge: float, gap: float = GAP_M) -> tuple[int, int, int, float, int,
                                                                       int]:
    """(junctions, wedges, isolated fragments, largest corner distance m, lane ends more than
    ``gap`` m from their junction's polygon, junction polygons that cross themselves) of one
    network."""
    import sumolib

    net = sumolib.net.readNet(str(net_file), withInternal=True)
    internal = collections.defaultdict(list)
    for e in net.getEdges(withInternal=True):
        if e.getFunction() == "internal":
            internal[e.getToNode().getID()].extend(e.getLanes())
    junctions = wedges = holes = crossed = 0
    worst = 0.0
    for node in net.getNodes():
        shape = node.getShape()
        lanes = internal.get(node.getID())
        if not lanes or not shape or len(shape) < 3:
            continue
        junctions += 1
        crossed += self_intersecting(np.asarray(shape)[:, :2])
        pts = [_dense(np.asarray(l.getShape())[:, :2]) for l in lanes]
        pts += [np.asarray(l.getShape())[:, :2] for e in node.getIncoming() + node.getOutgoing()
                if e.getFunction() != "internal" for l in e.getLanes()]
        pts = np.concatenate(pts)
        corners = np.asarray(shape)[:, :2]
        far = np.sqrt(((corners[:, None] - pts[None]) ** 2).sum(-1)).min(1).max()
        worst = max(worst, float(far))
        wedges += far > wedge
        ends = [np.asarray(l.getShape())[-1, :2] for e in node.getIncoming()
                if e.getFunction() != "internal" for l in e.getLanes()]
        ends += [np.asarray(l.getShape())[0, :2] for e in node.getOutgoing()
                 if e.getFunction() != "internal" for l in e.getLanes()]
        if ends:
            holes += int((outside_distance(np.array(ends), corners) > gap).sum())
    isolated = sum(1 for e in net.getEdges(withInternal=False)
                   if e.getFunction() != "walkingarea" and not e.getIncoming()
                   and not e.getOutgoing())
    return junctions, wedges, isolated, worst, holes, crossed


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dirs", nargs="+", type=Path)
    ap.add_argument("--wedge", type=float, default=15.0, help="m (default 15)")
    args = ap.parse_args()
    print("folder | source | scenes | junctions | wedges | isolated fragments | "
          "largest corner distance (m) | lane ends apart from their junction | "
          "polygons crossing themselves")
    for d in args.dirs:
        per = collections.defaultdict(lambda: [0, 0, 0, 0, 0.0, 0, 0])
        for rep_file in sorted(d.glob("*/conversion.json")):
            rep = json.loads(rep_file.read_text())
            nets = list(rep_file.parent.glob("*.net.xml"))
            if rep.get("status") != "ok" or not nets:
                continue
            src = Path((rep.get("source") or {}).get("file", "?")).parent.name
            j, w, i, far, h, x = measure(nets[0], args.wedge)
            row = per[src]
            row[0] += 1
            row[1] += j
            row[2] += w
            row[3] += i
            row[4] = max(row[4], far)
            row[5] += h
            row[6] += x
        total = [0, 0, 0, 0, 0.0, 0, 0]
        for src, row in sorted(per.items()):
            print(f"{d} | {src} | {row[0]} | {row[1]} | {row[2]} | {row[3]} | {row[4]:.0f} | "
                  f"{row[5]} | {row[6]}")
            total = [a + b for a, b in zip(total[:4], row[:4])] + [max(total[4], row[4]),
                                                                   total[5] + row[5],
                                                                   total[6] + row[6]]
        print(f"{d} | all | {total[0]} | {total[1]} | {total[2]} | {total[3]} | "
              f"{total[4]:.0f} | {total[5]} | {total[6]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
