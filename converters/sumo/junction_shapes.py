"""Junction polygons that reach every lane end: no hole between a road and its junction.

netconvert draws a junction's polygon from where it cuts the edges that meet there. The
converter gives every lane its recorded centre line, so the lanes do not always end where
netconvert's polygon begins: a lane piece split off mid-way along a recorded lane ends a few
metres short of its node (netconvert's polygon there is a line across the road), and where a
road forks the polygon leaves the gore between the branches open. sumo-gui then shows the
background between the lane ends and the junction (a *hole*); the internal lanes still join
the lanes, so SUMO's driving is not affected.

:func:`fill_junction_shapes` gives every junction with a lane end more than ``gap`` m outside
its polygon, or with a polygon that crosses itself, the convex hull of that polygon and of the end corners of all its lanes (each
incoming lane's last point and each outgoing lane's first point, offset by half the lane's
width to either side, across the lane's direction there). The hull's corners are lane corners
or netconvert's own corners, so it draws no spike along a road (no *wedge*). It is written into
the network file itself, as the junction's ``shape`` with ``customShape="1"`` (so netedit and a
later netconvert keep it): nothing else in the file changes, and no lane, internal lane or
right-of-way rule moves. Junctions whose polygon already reaches every lane end keep
netconvert's shape.

Frames and units: SUMO network coordinates (m).
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from .geometry import fmt_shape, segments_cross

#: a lane end this far (m) outside its junction's polygon is a hole (the benchmark's definition)
GAP_M = 1.0


def convex_hull(points: np.ndarray) -> np.ndarray:
    """(H, 2) corners of the convex hull of (P, 2) points, counter-clockwise, not closed
    (Andrew's monotone chain; collinear points dropped). Fewer than 3 distinct points: them.
    Plain Python: a junction has a few dozen points, where numpy's per-call cost dominates."""
    pts = sorted(set(map(tuple, np.round(np.asarray(points, np.float64)[:, :2], 6).tolist())))
    if len(pts) < 3:
        return np.array(pts, np.float64).reshape(-1, 2)

    def chain(seq: list[tuple[float, float]]) -> list[tuple[float, float]]:
        out: list[tuple[float, float]] = []
        for q in seq:
            while len(out) >= 2 and ((out[-1][0] - out[-2][0]) * (q[1] - out[-2][1])
                                     - (out[-1][1] - out[-2][1]) * (q[0] - out[-2][0])) <= 0:
                out.pop()
            out.append(q)
        return out

    return np.array(chain(pts)[:-1] + chain(pts[::-1])[:-1])


def outside_distance(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(P,) distance (m) of each point to the closed ``polygon`` (Q, 2); 0 inside it (even-odd
    rule; a degenerate polygon, e.g. a line, has no inside)."""
    pts = np.asarray(points, np.float64)[:, :2]
    a = np.asarray(polygon, np.float64)[:, :2]
    b = np.roll(a, -1, axis=0)
    ab = b - a
    rel = pts[:, None] - a[None]
    t = np.clip((rel * ab[None]).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12)[None], 0, 1)
    d = np.linalg.norm(rel - t[..., None] * ab[None], axis=-1).min(1)
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


def _shape(text: str | None) -> np.ndarray:
    if not text:
        return np.zeros((0, 2))
    return np.array([[float(v) for v in p.split(",")[:2]] for p in text.split()])


def _end_corners(shape: np.ndarray, width: float, at_end: bool) -> np.ndarray:
    """(2, 2) the corners of a lane's last (``at_end``) or first cross-section."""
    p, q = (shape[-1], shape[-2]) if at_end else (shape[0], shape[1])
    d = p - q if at_end else q - p
    n = float(np.hypot(*d))
    if n < 1e-9:
        return np.array([p, p])
    left = np.array([-d[1], d[0]]) / n * (width / 2)
    return np.array([p + left, p - left])


def filled_shapes(net_file: Path, gap: float = GAP_M) -> dict[str, np.ndarray]:
    """The new polygon (H, 2) of each junction of ``net_file`` with a lane end more than
    ``gap`` m outside its polygon or a polygon that crosses itself (see the module doc); the
    others are not listed."""
    junctions: dict[str, np.ndarray] = {}
    ends: dict[str, list[np.ndarray]] = {}
    # (shape, width, at its end) of each lane meeting a node: corners only where one is filled
    lanes: dict[str, list[tuple[np.ndarray, float, bool]]] = {}
    for _, el in ET.iterparse(str(net_file)):  # an element's end: its children are read
        tag = el.tag
        if tag == "edge" and el.get("function", "normal") == "normal":
            head, tail = el.get("to", ""), el.get("from", "")
            for lane in el.iter("lane"):
                shape = _shape(lane.get("shape"))
                if len(shape) < 2:
                    continue
                width = float(lane.get("width", 3.2))
                for node, at_end in ((head, True), (tail, False)):
                    ends.setdefault(node, []).append(shape[-1] if at_end else shape[0])
                    lanes.setdefault(node, []).append((shape, width, at_end))
        elif tag == "junction" and el.get("type") != "internal":
            junctions[el.get("id", "")] = _shape(el.get("shape"))
        if tag in ("edge", "junction", "connection", "tlLogic"):
            el.clear()
    out: dict[str, np.ndarray] = {}
    for jid, poly in junctions.items():
        if jid not in ends:
            continue
        lane_ends = np.array(ends[jid])
        if len(poly) >= 3 and not self_intersecting(poly) \
                and (outside_distance(lane_ends, poly) <= gap).all():
            continue
        hull = convex_hull(np.vstack([poly.reshape(-1, 2),
                                      *(_end_corners(*lane) for lane in lanes[jid])]))
        if len(hull) >= 3:
            out[jid] = hull
    return out


_JUNCTION = re.compile(r'^(\s*<junction id="([^"]*)")(.*?)(/?>)\s*$')
_SHAPE = re.compile(r' shape="[^"]*"')


def fill_junction_shapes(net_file: str | Path, gap: float = GAP_M) -> int:
    """Give the junctions of ``net_file`` (netconvert's output, one ``<junction>`` element a
    line) whose polygon leaves a lane end more than ``gap`` m outside or crosses itself the
    convex hull of their polygon and lane end corners (:func:`filled_shapes`), in place;
    returns how many junctions changed."""
    path = Path(net_file)
    shapes = filled_shapes(path, gap)
    if not shapes:
        return 0
    lines = path.read_text().splitlines(keepends=True)
    changed = 0
    for k, line in enumerate(lines):
        if "<junction " not in line:
            continue
        m = _JUNCTION.match(line)
        if m is None or m.group(2) not in shapes:
            continue
        hull = shapes[m.group(2)]
        closed = np.vstack([hull, hull[:1]])
        attr = f' shape="{fmt_shape(closed)}"'
        rest = _SHAPE.sub("", m.group(3)).replace(' customShape="1"', "")
        lines[k] = f'{m.group(1)}{rest}{attr} customShape="1"{m.group(4)}\n'
        changed += 1
    path.write_text("".join(lines))
    return changed
