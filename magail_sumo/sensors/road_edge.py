"""Road edges: signed distance from box corners to a scene's road edges, and off-road (the
WOSAC map feature; the env's road-edge off-road rule uses the same test).

The signed distance of a point is taken to the road-edge segment nearest in 3-D (with z
stretched ×3, so edges on other levels lose); it is the 2-D distance to that segment, negative
on the segment's left (on-road) side and positive on its right (off-road). Beyond a segment's
ends the sign is resolved with the neighbouring segment (max if the joint is convex, else min).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from magail_sumo.scene import Scene
from magail_sumo.sim.boxes import box_corners

from .raycast import SegmentGrid

#: Vertical stretch applied when choosing the nearest segment.
Z_STRETCH = 3.0
#: Squared 3-D gap (m²) between first and last point below which a polyline is a ring.
CYCLIC_THRESHOLD_SQ = 1.0
#: Distance above which a box corner is off-road (strict), metres.
OFFROAD_DISTANCE_THRESHOLD = 0.0
#: Fill value for invalid object steps.
INVALID_DISTANCE = -1e10
#: Smallest grid cell (m) of the nearest-segment search; the grid has at most _MAX_CELLS cells.
_MIN_CELL = 5.0
_MAX_CELLS = 1_000_000
#: Relative slack on the nearest distance so far when pruning (float32 rounding grows with it).
_SLACK = 1.0 + 1e-5


@dataclass(frozen=True, eq=False)
class RoadEdgeSegments:
    """Road-edge segments of a scene, flattened in map order.

    :param a, b: (S, 3) float32 start and end points.
    :param prior, next: (S,) int64 neighbouring segment used beyond the start / end (-1: none).
    :param convex_prior, convex_next: (S,) bool, whether the joint with that neighbour turns
        left (positive 2-D cross product).
    :param grid: the segments bucketed in square cells (xy) for the nearest-segment search.
    :param margin: metres the search adds to its pruning bounds for float32 rounding (1 cm
        plus 32 float32 ulps of the largest coordinate; the distance so far also gets 1e-5
        relative).
    """

    a: np.ndarray
    b: np.ndarray
    prior: np.ndarray
    next: np.ndarray
    convex_prior: np.ndarray
    convex_next: np.ndarray
    grid: SegmentGrid
    margin: float


def has_road_edges(scene: Scene) -> bool:
    """Whether the scene's map has a road edge with at least 2 points (the map features need
    one; real maps may have none, e.g. nuScenes ScenarioNet pickles)."""
    return any(len(e.polyline) >= 2 for e in scene.roadmap.road_edges)


def road_edge_segments(scene: Scene) -> RoadEdgeSegments:
    """Segments of every road edge with at least 2 points.

    A ring (first and last points within 1 m) wraps its end segments onto each other only when
    it has as many points as the longest kept edge; shorter rings end like open polylines, as
    in the official tool (which pads edges to a common length).

    :raises ValueError: the scene has no road edge with at least 2 points.
    """
    pls = [e.polyline.astype(np.float32) for e in scene.roadmap.road_edges
           if len(e.polyline) >= 2]
    if not pls:
        raise ValueError("missing road edges")
    most = max(len(p) for p in pls)
    a, b, prior, nxt = [], [], [], []
    start = 0
    for p in pls:
        n = len(p) - 1
        ring = len(p) == most and float(((p[0] - p[-1]) ** 2).sum()) < CYCLIC_THRESHOLD_SQ
        idx = np.arange(start, start + n)
        pr, nx = idx - 1, idx + 1
        pr[0] = start + n - 1 if ring else -1
        nx[-1] = start if ring else -1
        a.append(p[:-1]); b.append(p[1:]); prior.append(pr); nxt.append(nx)
        start += n
    a, b = np.concatenate(a), np.concatenate(b)
    prior, nxt = np.concatenate(prior), np.concatenate(nxt)
    d = (b - a)[:, :2]

    def cross(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        return d[i, 0] * d[j, 1] - d[i, 1] * d[j, 0] > 0

    s = np.arange(len(a))
    convex_prior = np.where(prior >= 0, cross(prior, s), False)
    convex_next = np.where(nxt >= 0, cross(s, nxt), False)
    xy = np.concatenate([a[:, :2], b[:, :2]]).astype(np.float64)
    span = xy.max(0) - xy.min(0)
    cell = max(_MIN_CELL, float(np.sqrt(span[0] * span[1] / _MAX_CELLS)), float(span.max()) / 4096)
    grid = SegmentGrid.build(a[:, :2], b[:, :2], cell)
    margin = 0.01 + 4e-6 * float(np.abs(xy).max())
    return RoadEdgeSegments(a, b, prior, nxt, convex_prior, convex_next, grid, margin)


@numba.njit(cache=True, inline="always")
def _side(qx, qy, ax, ay, bx, by):  # pragma: no cover - numba
    c = (qx - ax) * (by - ay) - (qy - ay) * (bx - ax)
    return np.float32(1.0) if c > 0 else (np.float32(-1.0) if c < 0 else np.float32(0.0))


@numba.njit(cache=True, inline="always")
def _segment_d3(qx, qy, qz, a, b, s):  # pragma: no cover - numba
    """Squared 3-D distance (z stretched) from the point to segment ``s`` (float32)."""
    dx, dy, dz = b[s, 0] - a[s, 0], b[s, 1] - a[s, 1], b[s, 2] - a[s, 2]
    px, py, pz = qx - a[s, 0], qy - a[s, 1], qz - a[s, 2]
    den = dx * dx + dy * dy
    t = (px * dx + py * dy) / den if den != 0 else np.float32(0.0)
    tc = min(max(t, np.float32(0.0)), np.float32(1.0))
    ox, oy, oz = px - dx * tc, py - dy * tc, (pz - dz * tc) * np.float32(Z_STRETCH)
    return ox * ox + oy * oy + oz * oz


@numba.njit(cache=True, inline="always")
def _visit(qx, qy, qz, a, b, x0, y0, cell, ny, offsets, items, margin, gx, gy, best, bi
           ):  # pragma: no cover - numba
    """The nearest (d3, segment) so far after the segments of cell (gx, gy), unless no point
    of the cell is within reach (the best distance plus the margin)."""
    c = gx * ny + gy
    if offsets[c] == offsets[c + 1]:
        return best, bi
    ex = max(x0 + gx * cell - qx, 0.0, qx - (x0 + (gx + 1) * cell))
    ey = max(y0 + gy * cell - qy, 0.0, qy - (y0 + (gy + 1) * cell))
    reach = np.sqrt(np.float64(best)) * _SLACK + margin
    if ex * ex + ey * ey > reach * reach:
        return best, bi
    for m in range(offsets[c], offsets[c + 1]):
        s = items[m]
        d3 = _segment_d3(qx, qy, qz, a, b, s)
        if d3 < best or (d3 == best and s < bi):
            best = d3
            bi = s
    return best, bi


@numba.njit(cache=True, parallel=True)
def _signed_distance(q, a, b, prior, nxt, cvp, cvn, x0, y0, cell, nx, ny, offsets, items,
                     margin):  # pragma: no cover - numba
    n = q.shape[0]
    out = np.empty(n, np.float32)
    gx1, gy1 = x0 + nx * cell, y0 + ny * cell
    for i in numba.prange(n):
        qx, qy, qz = q[i, 0], q[i, 1], q[i, 2]
        best = np.float32(np.inf)
        bi = -1
        # rings of cells around the (clamped) cell of the point, nearest first; a segment
        # wins with the smallest d3, the lowest index among equal ones (as a scan in order)
        px = min(max(np.float64(qx), x0), gx1)
        py = min(max(np.float64(qy), y0), gy1)
        cx = min(max(int(np.floor((px - x0) / cell)), 0), nx - 1)
        cy = min(max(int(np.floor((py - y0) / cell)), 0), ny - 1)
        out_sq = (np.float64(qx) - px) ** 2 + (np.float64(qy) - py) ** 2
        rings = max(nx, ny) + 1
        if not (np.isfinite(qx) and np.isfinite(qy) and np.isfinite(qz)):
            rings = 0  # no finite distance: segment 0, as a scan finds no smaller one
        for k in range(rings):
            if k > 0 and bi >= 0:
                # every cell of ring k lies outside the box of rings < k around p, the
                # projection of the point onto the grid, and for a point c of the grid
                # |q - c|^2 >= |q - p|^2 + |p - c|^2 (projection onto a convex set)
                lb = min(px - (x0 + (cx - k + 1) * cell), x0 + (cx + k) * cell - px,
                         py - (y0 + (cy - k + 1) * cell), y0 + (cy + k) * cell - py)
                reach = np.sqrt(np.float64(best)) * _SLACK + margin
                if lb * lb + out_sq > reach * reach:
                    break
            for gx in range(max(cx - k, 0), min(cx + k, nx - 1) + 1):
                if gx == cx - k or gx == cx + k:  # a side column of the ring: all its cells
                    for gy in range(max(cy - k, 0), min(cy + k, ny - 1) + 1):
                        best, bi = _visit(qx, qy, qz, a, b, x0, y0, cell, ny, offsets, items,
                                          margin, gx, gy, best, bi)
                else:  # an inner column: its bottom and top cells
                    if cy - k >= 0:
                        best, bi = _visit(qx, qy, qz, a, b, x0, y0, cell, ny, offsets, items,
                                          margin, gx, cy - k, best, bi)
                    if cy + k < ny:
                        best, bi = _visit(qx, qy, qz, a, b, x0, y0, cell, ny, offsets, items,
                                          margin, gx, cy + k, best, bi)
        s = max(bi, 0)
        dx, dy = b[s, 0] - a[s, 0], b[s, 1] - a[s, 1]
        px32, py32 = qx - a[s, 0], qy - a[s, 1]
        den = dx * dx + dy * dy
        t = (px32 * dx + py32 * dy) / den if den != 0 else np.float32(0.0)
        tc = min(max(t, np.float32(0.0)), np.float32(1.0))
        ox, oy = px32 - dx * tc, py32 - dy * tc
        sign = _side(qx, qy, a[s, 0], a[s, 1], b[s, 0], b[s, 1])
        if t < 0 and prior[s] >= 0:
            p = prior[s]
            other = _side(qx, qy, a[p, 0], a[p, 1], b[p, 0], b[p, 1])
            sign = max(sign, other) if cvp[s] else min(sign, other)
        elif t > 1 and nxt[s] >= 0:
            p = nxt[s]
            other = _side(qx, qy, a[p, 0], a[p, 1], b[p, 0], b[p, 1])
            sign = max(sign, other) if cvn[s] else min(sign, other)
        out[i] = sign * np.sqrt(ox * ox + oy * oy)
    return out


def signed_distance_to_road_edge(points: np.ndarray, segs: RoadEdgeSegments) -> np.ndarray:
    """Signed 2-D distance (m, positive off-road) of (..., 3) float32 points.

    The nearest segment is searched in rings of grid cells around each point (numba), nearest
    ring first, until no unvisited cell can hold a nearer one: the same segment as a scan over
    all segments (the lowest index among equally near ones), hence the same distance. A point
    equal (bit for bit) to the one before it in C order reuses its distance."""
    q = np.ascontiguousarray(points, np.float32).reshape(-1, 3)
    new = np.ones(len(q), bool)
    bits = q.view(np.int32)
    new[1:] = (bits[1:] != bits[:-1]).any(1)
    g = segs.grid
    out = _signed_distance(q[new], segs.a, segs.b, segs.prior, segs.next, segs.convex_prior,
                           segs.convex_next, g.x0, g.y0, g.cell, g.nx, g.ny, g.offsets, g.items,
                           segs.margin)
    return out[np.cumsum(new) - 1].reshape(points.shape[:-1])


def distance_to_road_edge(x, y, z, heading, length, width, height, valid,
                          segs: RoadEdgeSegments) -> np.ndarray:
    """Signed distance (m) of each box's most off-road bottom corner; -1e10 where invalid.

    :param x, y, z, heading, valid: (B, E, T); ``length, width, height``: (E, T).
    """
    cx, cy = box_corners(x, y, heading, np.broadcast_to(length, x.shape),
                         np.broadcast_to(width, x.shape))
    cz = np.broadcast_to((z - height / 2)[..., None], cx.shape)
    # valid steps only, steps last: a pose held over steps (a stopped car) repeats its corners
    corners = np.moveaxis(np.stack([cx, cy, cz], -1), 3, 2)  # (B, E, 4, T, 3)
    keep = np.broadcast_to(valid[:, :, None, :], corners.shape[:-1])
    d = np.full(keep.shape, np.float32(INVALID_DISTANCE))
    d[keep] = signed_distance_to_road_edge(corners[keep], segs)
    return np.where(valid, d.max(2), np.float32(INVALID_DISTANCE))
