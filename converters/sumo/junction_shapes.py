"""Junction polygons that reach their lane ends: no hole between a road and its junction.

netconvert draws a junction's polygon from where it cuts the edges that meet there. The
converter gives every lane its recorded centre line, so the lanes do not always end where
netconvert's polygon begins: a lane piece split off mid-way along a recorded lane ends a few
metres short of its node (netconvert's polygon there is a line across the road), and where a
road forks the polygon leaves the gore between the branches open. sumo-gui then shows the
background between the lane ends and the junction (a *hole*); the internal lanes still join
the lanes, so SUMO's driving is not affected. Where lanes meet at awkward angles (nuScenes
crossings, four lanes ending together) netconvert's polygon can also cross itself, drawn as a
ragged star or a bow tie with holes.

:func:`fill_junction_shapes` gives every junction whose polygon leaves a lane end more than
``gap`` m outside, crosses itself (is not a valid polygon) or has fewer than 3 points the ground
its pieces cover, closed: the union of its internal lanes (each centre line widened to the
lane's width), a strip across the end of each lane meeting there and netconvert's polygon (its
valid part), grown by ``close`` m and shrunk back by as much. That closes the gaps narrower
than twice ``close`` (a line-shaped polygon, a fork's gore, the holes of a star) and follows the
roads elsewhere; a convex hull would span the ground between carriageways where a junction's
lanes end far apart. Holes inside are dropped. A part left apart (a lane end with no
connection at that junction) is joined to the largest part by the convex hull of the part and
the largest part's ground near it when it lies within ``BRIDGE_M`` m, and left out beyond (that
lane's internal lane is drawn over the gap). The result draws no spike along a road (no
*wedge*). It is written into the network file itself, as the junction's ``shape`` with
``customShape="1"`` (netedit and a later netconvert keep it): nothing else in the file changes,
and no lane, internal lane or right-of-way rule moves. Junctions whose polygon already reaches
every lane end keep netconvert's shape.

Frames and units: SUMO network coordinates (m).
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from .geometry import fmt_shape

#: a lane end this far (m) outside its junction's polygon is a hole (the benchmark's definition)
GAP_M = 1.0
#: gaps (m) narrower than twice this between the pieces of a junction are closed
#: (morphological closing: grown by it, then shrunk by it)
CLOSE_M = 2.0
#: depth (m) of the strip across each lane end that the filled shape covers on either side
END_DEPTH_M = 0.25
#: tolerance (m) of the filled polygon's simplification
SIMPLIFY_M = 0.05
#: a part of a junction's ground farther (m) than this from its largest part is left out
#: (a lane end joined by a long internal lane: the lane is drawn over the gap)
BRIDGE_M = 10.0


def _shape(text: str | None) -> np.ndarray:
    """(P, 2) points of a SUMO ``shape`` attribute ("x,y x,y ..." or with z)."""
    if not text:
        return np.zeros((0, 2))
    dims = text.split(" ", 1)[0].count(",") + 1
    return np.array(text.replace(",", " ").split(), np.float64).reshape(-1, dims)[:, :2]


def _end_corners(shape: np.ndarray, width: float, at_end: bool) -> np.ndarray:
    """(2, 2) the corners of a lane's last (``at_end``) or first cross-section."""
    p, q = (shape[-1], shape[-2]) if at_end else (shape[0], shape[1])
    d = p - q if at_end else q - p
    n = float(np.hypot(*d))
    if n < 1e-9:
        return np.array([p, p])
    left = np.array([-d[1], d[0]]) / n * (width / 2)
    return np.array([p + left, p - left])


def _bridged(parts) -> object:
    """One polygon of a junction's parts (a MultiPolygon): each part within ``BRIDGE_M`` m of
    the largest joined to it by the convex hull of the part and the largest's ground within
    half the part's size of its nearest point (a lane end with no connection there, a few
    metres off: the bridge is as wide as the lane, no sliver); farther parts dropped."""
    import shapely
    from shapely.geometry import MultiPoint
    from shapely.ops import nearest_points

    geoms = sorted(parts.geoms, key=lambda g: -g.area)
    main = geoms[0]
    joined = [main]
    for part in geoms[1:]:
        if main.distance(part) > BRIDGE_M:
            continue
        near = nearest_points(main, part)[0]
        reach = max(1.0, float(np.ptp(np.asarray(part.exterior.coords), axis=0).max()) / 2)
        patch = main.intersection(near.buffer(reach, quad_segs=4))  # as wide as the part
        joined.append(MultiPoint([*part.exterior.coords,
                                  *shapely.get_coordinates(patch)]).convex_hull)
    area = shapely.union_all(joined)
    if not isinstance(area, shapely.geometry.Polygon):  # touching only at a point
        return main
    return area


def filled_shapes(net_file: Path, gap: float = GAP_M,
                  close: float = CLOSE_M) -> dict[str, np.ndarray]:
    """The new polygon (H, 2) of each junction of ``net_file`` to fill: a lane end more than
    ``gap`` m outside its polygon, a polygon that is not valid or of under 3 points (see the
    module doc); the others are not listed."""
    import shapely
    from shapely.geometry import MultiPolygon, Polygon

    junctions: dict[str, np.ndarray] = {}
    ends: dict[str, list[np.ndarray]] = {}
    # (shape, width, at its end) of each lane meeting a node; (shape, width) of its internal lanes
    lanes: dict[str, list[tuple[np.ndarray, float, bool]]] = {}
    internal: dict[str, list[tuple[np.ndarray, float]]] = {}
    for _, el in ET.iterparse(str(net_file)):  # an element's end: its children are read
        tag = el.tag
        if tag == "edge":
            function = el.get("function", "normal")
            if function == "normal":
                head, tail = el.get("to", ""), el.get("from", "")
                for lane in el.iter("lane"):
                    shape = _shape(lane.get("shape"))
                    if len(shape) < 2:
                        continue
                    width = float(lane.get("width", 3.2))
                    for node, at_end in ((head, True), (tail, False)):
                        ends.setdefault(node, []).append(shape[-1] if at_end else shape[0])
                        lanes.setdefault(node, []).append((shape, width, at_end))
            elif function == "internal":  # ":<junction>_<k>"
                node = el.get("id", "")[1:].rsplit("_", 1)[0]
                for lane in el.iter("lane"):
                    shape = _shape(lane.get("shape"))
                    if len(shape) >= 2:
                        internal.setdefault(node, []).append(
                            (shape, float(lane.get("width", 3.2))))
        elif tag == "junction" and el.get("type") != "internal":
            junctions[el.get("id", "")] = _shape(el.get("shape"))
        if tag in ("edge", "junction", "connection", "tlLogic"):
            el.clear()
    # to fill: a polygon of under 3 points, one that is not valid (crosses itself), or one
    # with a lane end more than ``gap`` m outside (all junctions in one vectorised pass)
    ids = [jid for jid, poly in junctions.items() if jid in ends and len(poly)]
    polys = np.array([Polygon(junctions[j]) if len(junctions[j]) >= 3 else None for j in ids],
                     dtype=object)
    bad = ~shapely.is_valid(polys)  # None (under 3 points) is not valid either
    end_owner = np.repeat(np.arange(len(ids)), [len(ends[j]) for j in ids])
    end_xy = np.concatenate([np.asarray(ends[j]) for j in ids]) if ids else np.zeros((0, 2))
    far = shapely.distance(polys[end_owner], shapely.points(end_xy)) > gap  # NaN: no polygon
    bad |= np.bincount(end_owner[far], minlength=len(ids)) > 0
    picked = np.flatnonzero(bad)
    todo = [ids[k] for k in picked]
    if not todo:
        return {}
    # every piece of every junction to fill, built in one vectorised call per kind
    lines, widths, owner = [], [], []
    for k, jid in enumerate(todo):
        for shape, width in internal.get(jid, ()):
            lines.append(shape)
            widths.append(width)
            owner.append(k)
        for lane in lanes[jid]:
            lines.append(_end_corners(*lane))
            widths.append(2 * END_DEPTH_M)
            owner.append(k)
    strings = shapely.linestrings(np.concatenate(lines),
                                  indices=np.repeat(np.arange(len(lines)), [len(x) for x in lines]))
    pieces = shapely.buffer(strings, np.asarray(widths) / 2, cap_style="flat")
    # netconvert's polygons, their polygonal parts only (make_valid keeps a zero-width spike
    # as a line); None where it drew under 3 points
    groups: list[list] = [[poly] for poly in
                          shapely.buffer(shapely.make_valid(polys[picked]), 0)]
    for k, piece in zip(owner, pieces):
        groups[k].append(piece)
    table = np.full((len(groups), max(len(g) for g in groups)), None, dtype=object)
    for k, g in enumerate(groups):  # one row per junction, padded with None (ignored)
        table[k, :len(g)] = g
    areas = shapely.simplify(shapely.union_all(table, axis=1), SIMPLIFY_M)
    areas = shapely.buffer(shapely.buffer(areas, close, quad_segs=2), -close, quad_segs=2)
    areas = np.array([_bridged(a) if isinstance(a, MultiPolygon) else a for a in areas],
                     dtype=object)  # parts more than 2 x close apart joined
    ok = shapely.get_type_id(areas) == 3  # Polygon
    # without holes, necks under 0.1 m widened, valid on the written 0.01 m grid
    rings = shapely.simplify(shapely.polygons(shapely.get_exterior_ring(areas[ok])), SIMPLIFY_M)
    rings = shapely.buffer(shapely.buffer(rings, 0.05, quad_segs=2), -0.05, quad_segs=2)
    rings = shapely.set_precision(rings, 0.01)
    out: dict[str, np.ndarray] = {}
    for jid, area in zip(np.asarray(todo, dtype=object)[ok], rings):
        if isinstance(area, MultiPolygon):  # split at a neck by the rounding: bridged again
            area = shapely.set_precision(_bridged(area), 0.01)
        if isinstance(area, MultiPolygon):
            area = max(area.geoms, key=lambda g: g.area)
        if not isinstance(area, Polygon) or area.is_empty:
            continue
        ring = np.asarray(area.exterior.coords)[:-1]
        if len(ring) >= 3:
            out[jid] = ring[:, :2]
    return out


_JUNCTION = re.compile(r'^(\s*<junction id="([^"]*)")(.*?)(/?>)\s*$')
_SHAPE = re.compile(r' shape="[^"]*"')


def fill_junction_shapes(net_file: str | Path, gap: float = GAP_M,
                         close: float = CLOSE_M) -> int:
    """Give the junctions of ``net_file`` (netconvert's output, one ``<junction>`` element a
    line) whose polygon leaves a lane end more than ``gap`` m outside or crosses itself the
    shape :func:`filled_shapes` gives, in place; returns how many junctions changed."""
    path = Path(net_file)
    shapes = filled_shapes(path, gap, close)
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
        ring = shapes[m.group(2)]
        closed = np.vstack([ring, ring[:1]])
        attr = f' shape="{fmt_shape(closed)}"'
        rest = _SHAPE.sub("", m.group(3)).replace(' customShape="1"', "")
        lines[k] = f'{m.group(1)}{rest}{attr} customShape="1"{m.group(4)}\n'
        changed += 1
    path.write_text("".join(lines))
    return changed
