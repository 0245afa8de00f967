"""2-D ray casting over all agents of a step at once (numba kernels, no per-beam Python loops).

Frames: scene frame, metres. A ray starts at an agent's origin and points along an angle
(radians, counter-clockwise from +x); its reading is the distance to the first segment it hits,
or ``max_range`` when it hits nothing within range.

Two kinds of geometry:

* dynamic segments (other road users' boxes, rebuilt every step): each agent is tested against
  every segment after a cheap distance cull — O(A·S) cull, fine for thousands of agents;
* static segments (road edges, lane lines): indexed once in a :class:`SegmentGrid` so an agent
  only visits the cells around it.

Segments carry an owner id; an agent never sees segments of its own id (its own box).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

_EPS = 1e-12


def box_edges(center: np.ndarray, half_extent: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """The 4 edges of oriented boxes.

    :param center: (N, 2) box centres.
    :param half_extent: (N, 2) half length (along heading) and half width.
    :param heading: (N,) box yaw in radians.
    :returns: (N, 4, 2, 2) edges as (start, end) points, counter-clockwise.
    """
    c, s = np.cos(heading), np.sin(heading)
    fwd = np.stack([c, s], axis=-1) * half_extent[:, :1]
    left = np.stack([-s, c], axis=-1) * half_extent[:, 1:2]
    corners = np.stack([center + fwd + left, center - fwd + left, center - fwd - left,
                        center + fwd - left], axis=1)
    return np.stack([corners, np.roll(corners, -1, axis=1)], axis=2)


def polyline_segments(polylines: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Consecutive-point segments of (P, >=2) polylines as (S, 2) start and end arrays."""
    starts, ends, _ = indexed_polyline_segments(polylines)
    return starts, ends


def indexed_polyline_segments(polylines: list[np.ndarray]
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`polyline_segments` plus the (S,) index of the polyline each segment belongs to
    (polylines of fewer than 2 points give no segment)."""
    counts = np.array([max(len(p) - 1, 0) for p in polylines], np.int64)
    owner = np.repeat(np.arange(len(polylines), dtype=np.int64), counts)
    parts = [p[:, :2] for p in polylines if len(p) > 1]
    if not parts:
        return np.zeros((0, 2)), np.zeros((0, 2)), owner
    return (np.ascontiguousarray(np.concatenate([p[:-1] for p in parts]), np.float64),
            np.ascontiguousarray(np.concatenate([p[1:] for p in parts]), np.float64), owner)


@numba.njit(cache=True, inline="always")
def _hit(ox, oy, dx, dy, ax, ay, bx, by):
    """Distance along the unit ray (o, d) to segment a-b, or inf."""
    ex, ey = bx - ax, by - ay
    px, py = ax - ox, ay - oy
    denom = dx * ey - dy * ex
    u_num = px * dy - py * dx
    if abs(denom) > _EPS:
        t = (px * ey - py * ex) / denom
        u = u_num / denom
        if t >= 0.0 and 0.0 <= u <= 1.0:
            return t
        return np.inf
    if abs(u_num) > 1e-9:  # parallel, not collinear
        return np.inf
    ts = px * dx + py * dy  # collinear: nearest end point ahead (0 if the origin is on it)
    te = (bx - ox) * dx + (by - oy) * dy
    lo, hi = min(ts, te), max(ts, te)
    if lo >= 0.0:
        return lo
    if hi >= 0.0:
        return 0.0
    return np.inf


@numba.njit(cache=True, inline="always")
def cell_gap(g, c, f, cell):
    """Distance (m) along one axis from a point at grid coordinate ``f`` (in cell ``c``) to
    grid cell ``g``: 0 in its own cell, else to the cell's near side."""
    return 0.0 if g == c else ((g - f) if g > c else (f - g - 1.0)) * cell


@numba.njit(cache=True, inline="always")
def _seg_dist2(x, y, ax, ay, bx, by):
    ex, ey = bx - ax, by - ay
    wx, wy = x - ax, y - ay
    ll = ex * ex + ey * ey
    t = 0.0 if ll < _EPS else min(1.0, max(0.0, (wx * ex + wy * ey) / ll))
    qx, qy = wx - t * ex, wy - t * ey
    return qx * qx + qy * qy


@numba.njit(cache=True, inline="always")
def _cast_segment(out, i, ox, oy, angles, cosb, sinb, uniform, step, full, ax, ay, bx, by):
    """Fold segment a-b into agent i's readings: every beam, or with evenly spaced beams
    (``uniform``; beam j along angles[i, 0] + j·step) only those inside the segment's span."""
    if uniform:
        _cast_window(out, i, ox, oy, angles[i, 0], step, full, cosb, sinb, ax, ay, bx, by)
        return
    for j in range(out.shape[1]):
        t = _hit(ox, oy, cosb[i, j], sinb[i, j], ax, ay, bx, by)
        if t < out[i, j]:
            out[i, j] = t


@numba.njit(cache=True, inline="always")
def _cast_window(out, i, ox, oy, theta0, step, full, cosb, sinb, ax, ay, bx, by):
    """Test only the beams whose direction falls inside the segment's angular span as seen
    from the origin (uniformly spaced beams: beam j points along theta0 + j·step)."""
    b = out.shape[1]
    a1 = np.arctan2(ay - oy, ax - ox)
    a2 = np.arctan2(by - oy, bx - ox)
    span = (a2 - a1 + np.pi) % (2.0 * np.pi) - np.pi
    if abs(span) > np.pi - 1e-6:  # the origin (nearly) lies on the segment: test every beam
        for j in range(b):
            t = _hit(ox, oy, cosb[i, j], sinb[i, j], ax, ay, bx, by)
            if t < out[i, j]:
                out[i, j] = t
        return
    lo = a1 if span >= 0.0 else a2
    width = abs(span)
    rel = (lo - theta0) % (2.0 * np.pi)
    for shift in (0.0, -2.0 * np.pi):
        r = rel + shift
        j0 = int(np.ceil((r - 1e-7) / step))
        j1 = int(np.floor((r + width + 1e-7) / step))
        for jj in range(j0, j1 + 1):
            if full:
                j = jj % b
            else:
                if jj < 0 or jj >= b:
                    continue
                j = jj
            t = _hit(ox, oy, cosb[i, j], sinb[i, j], ax, ay, bx, by)
            if t < out[i, j]:
                out[i, j] = t
        if full:
            break


@numba.njit(cache=True)
def _cast_all(origins, angles, uniform, step, full, max_range, starts, ends, seg_owner,
              agent_owner):
    a, b = angles.shape
    out = np.full((a, b), max_range)
    cosb, sinb = np.cos(angles), np.sin(angles)
    r2 = max_range * max_range
    for i in range(a):
        ox, oy = origins[i, 0], origins[i, 1]
        for k in range(starts.shape[0]):
            if seg_owner[k] == agent_owner[i]:
                continue
            ax, ay, bx, by = starts[k, 0], starts[k, 1], ends[k, 0], ends[k, 1]
            if _seg_dist2(ox, oy, ax, ay, bx, by) > r2:
                continue
            _cast_segment(out, i, ox, oy, angles, cosb, sinb, uniform, step, full, ax, ay, bx, by)
    return out


@numba.njit(cache=True)
def _cast_grid(origins, angles, uniform, step, full, max_range, starts, ends, seg_owner,
               agent_owner, x0, y0, cell, nx, ny, offsets, items):
    a, b = angles.shape
    out = np.full((a, b), max_range)
    cosb, sinb = np.cos(angles), np.sin(angles)
    r2 = max_range * max_range
    reach = int(np.ceil(max_range / cell))
    seen = np.full(starts.shape[0], -1, np.int64)
    for i in range(a):
        ox, oy = origins[i, 0], origins[i, 1]
        fx = (ox - x0) / cell
        fy = (oy - y0) / cell
        cx = int(np.floor(fx))
        cy = int(np.floor(fy))
        for gx in range(max(cx - reach, 0), min(cx + reach + 1, nx)):
            dx = cell_gap(gx, cx, fx, cell)
            for gy in range(max(cy - reach, 0), min(cy + reach + 1, ny)):
                dy = cell_gap(gy, cy, fy, cell)
                if dx * dx + dy * dy > r2:
                    continue
                c = gx * ny + gy
                for m in range(offsets[c], offsets[c + 1]):
                    k = items[m]
                    if seen[k] == i or seg_owner[k] == agent_owner[i]:
                        continue
                    seen[k] = i
                    ax, ay, bx, by = starts[k, 0], starts[k, 1], ends[k, 0], ends[k, 1]
                    if _seg_dist2(ox, oy, ax, ay, bx, by) > r2:
                        continue
                    _cast_segment(out, i, ox, oy, angles, cosb, sinb, uniform, step, full, ax, ay,
                                  bx, by)
    return out


@numba.njit(cache=True)
def _cast_boxes(origins, angles, uniform, step, full, max_range, starts, ends, agent_box,
                box_world, offsets, rows, centre, reach):
    """:func:`_cast_all` against box edges (box ``j``'s edges are rows ``4j .. 4j + 3``),
    each agent visiting only its world's boxes and the shared ones
    (:class:`~magail_sumo.sensors.worlds.BoxGroups` buckets), never its own; a box whose
    centre is farther than ``reach[j]`` (range plus its half diagonal) is skipped whole (none
    of its edges comes within range), and of a box the origin is outside of only the edges
    facing the origin are cast (a ray's first hit on a convex box is on one of them)."""
    a, b = angles.shape
    out = np.full((a, b), max_range)
    cosb, sinb = np.cos(angles), np.sin(angles)
    r2 = max_range * max_range
    shared = offsets.shape[0] - 2
    facing = np.empty(4)  # per edge of the box at hand: > 0 (= 0) faces (runs by) the origin
    for i in range(a):
        ox, oy = origins[i, 0], origins[i, 1]
        me = agent_box[i]
        for bucket in (box_world[me], shared):
            for m in range(offsets[bucket], offsets[bucket + 1]):
                j = rows[m]
                if j == me:
                    continue
                cx, cy = centre[j, 0] - ox, centre[j, 1] - oy
                if cx * cx + cy * cy > reach[j] * reach[j]:
                    continue
                # from outside a convex box a ray first meets an edge facing the origin (the
                # corners run counter-clockwise: outward normal (ey, -ex)); from inside, any
                inside = True
                for e in range(4):
                    k = 4 * j + e
                    facing[e] = (ox - starts[k, 0]) * (ends[k, 1] - starts[k, 1]) - \
                        (oy - starts[k, 1]) * (ends[k, 0] - starts[k, 0])
                    inside = inside and facing[e] < 0.0
                for e in range(4):
                    if not inside and facing[e] < 0.0:
                        continue
                    k = 4 * j + e
                    ax, ay, bx, by = starts[k, 0], starts[k, 1], ends[k, 0], ends[k, 1]
                    if _seg_dist2(ox, oy, ax, ay, bx, by) > r2:
                        continue
                    _cast_segment(out, i, ox, oy, angles, cosb, sinb, uniform, step, full, ax,
                                  ay, bx, by)
    return out


def _uniform(angles: np.ndarray) -> tuple[float, bool]:
    """(spacing, full circle) when every row's beams are evenly spaced by the same step;
    (0.0, False) otherwise."""
    b = angles.shape[1]
    if b < 2 or angles.shape[0] == 0:
        return 0.0, False
    d = angles[:, 1:] - angles[:, :-1]
    step = float(d[0, 0])
    if step <= 0 or float(np.abs(d - step).max()) > 1e-9:  # (np.allclose costs ~50 µs here)
        return 0.0, False
    full = abs(step * b - 2.0 * np.pi) < 1e-9
    if not full and step * (b - 1) >= 2.0 * np.pi:
        return 0.0, False
    return step, full


def cast(origins: np.ndarray, angles: np.ndarray, max_range: float, starts: np.ndarray,
         ends: np.ndarray, seg_owner: np.ndarray | None = None,
         agent_owner: np.ndarray | None = None) -> np.ndarray:
    """Ray readings of every agent against dynamic segments.

    :param origins: (A, 2) ray origins.
    :param angles: (A, B) ray angles (rad, scene frame).
    :param max_range: reading when nothing is hit (m).
    :param starts, ends: (S, 2) segments.
    :param seg_owner: (S,) owner id of each segment (e.g. box index); -1 = nobody.
    :param agent_owner: (A,) owner id of each agent; its own segments are skipped.
    :returns: (A, B) float64 distances in [0, max_range].
    """
    s = starts.shape[0]
    a = origins.shape[0]
    so = np.full(s, -1, np.int64) if seg_owner is None else np.asarray(seg_owner, np.int64)
    ao = np.full(a, -2, np.int64) if agent_owner is None else np.asarray(agent_owner, np.int64)
    ang = np.ascontiguousarray(angles, np.float64)
    step, full = _uniform(ang)  # evenly spaced beams: each segment only visits the beams it spans
    out = _cast_all(np.ascontiguousarray(origins, np.float64), ang, step > 0.0, step, full,
                    float(max_range), np.ascontiguousarray(starts, np.float64),
                    np.ascontiguousarray(ends, np.float64), so, ao)
    return np.minimum(out, max_range)


def cast_boxes(origins: np.ndarray, angles: np.ndarray, max_range: float, starts: np.ndarray,
               ends: np.ndarray, agent_box: np.ndarray, groups) -> np.ndarray:
    """Ray readings of every agent against the edges of boxes of several worlds: as
    :func:`cast` with segment ``k`` owned by box ``k // 4`` (the layout of
    :meth:`~magail_sumo.sensors.base.Boxes.edges`), each agent (box row ``agent_box``) seeing
    only its world's boxes and the shared ones of ``groups``
    (:class:`~magail_sumo.sensors.worlds.BoxGroups`). The same readings as :func:`cast` of
    each world's boxes alone (a minimum over the same hits)."""
    ang = np.ascontiguousarray(angles, np.float64)
    step, full = _uniform(ang)
    starts = np.ascontiguousarray(starts, np.float64)
    corners = starts.reshape(-1, 4, 2)  # an edge starts at each corner
    centre = corners.mean(axis=1)
    half_diag = np.sqrt(((corners - centre[:, None, :]) ** 2).sum(axis=2)).max(axis=1) \
        if corners.shape[0] else np.zeros(0)
    reach = float(max_range) + half_diag + 1e-6
    out = _cast_boxes(np.ascontiguousarray(origins, np.float64), ang, step > 0.0, step, full,
                      float(max_range), starts, np.ascontiguousarray(ends, np.float64),
                      np.ascontiguousarray(agent_box, np.int64), groups.world, groups.offsets,
                      groups.rows, centre, reach)
    return np.minimum(out, max_range)


@dataclass(frozen=True)
class SegmentGrid:
    """Static segments bucketed in square cells of side ``cell`` (any sensor range; the range
    itself is a good choice).

    A segment is listed in every cell its bounding box overlaps; a cast visits, for each agent,
    the cells that come within ``max_range`` of it and tests each segment found there once (a
    long segment listed in several of those cells is not tested again).
    """

    starts: np.ndarray
    ends: np.ndarray
    x0: float
    y0: float
    cell: float
    nx: int
    ny: int
    offsets: np.ndarray
    items: np.ndarray

    @classmethod
    def build(cls, starts: np.ndarray, ends: np.ndarray, cell: float) -> "SegmentGrid":
        starts = np.ascontiguousarray(starts, np.float64).reshape(-1, 2)
        ends = np.ascontiguousarray(ends, np.float64).reshape(-1, 2)
        if starts.shape[0] == 0:
            return cls(starts, ends, 0.0, 0.0, float(cell), 1, 1, np.zeros(2, np.int64),
                       np.zeros(0, np.int64))
        lo = np.minimum(starts, ends)
        hi = np.maximum(starts, ends)
        x0, y0 = lo.min(axis=0)
        nx = int((hi[:, 0].max() - x0) // cell) + 1
        ny = int((hi[:, 1].max() - y0) // cell) + 1
        c_lo = ((lo - (x0, y0)) // cell).astype(np.int64)
        c_hi = ((hi - (x0, y0)) // cell).astype(np.int64)
        span = (c_hi - c_lo + 1)
        counts = span[:, 0] * span[:, 1]
        seg = np.repeat(np.arange(starts.shape[0]), counts)
        local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        gx = c_lo[seg, 0] + local // span[seg, 1]
        gy = c_lo[seg, 1] + local % span[seg, 1]
        cell_id = gx * ny + gy
        order = np.argsort(cell_id, kind="stable")
        offsets = np.zeros(nx * ny + 1, np.int64)
        np.add.at(offsets, cell_id + 1, 1)
        return cls(starts, ends, float(x0), float(y0), float(cell), nx, ny, np.cumsum(offsets),
                   seg[order].astype(np.int64))

    def cast(self, origins: np.ndarray, angles: np.ndarray, max_range: float,
             seg_owner: np.ndarray | None = None, agent_owner: np.ndarray | None = None
             ) -> np.ndarray:
        """(A, B) ray readings against the gridded segments.

        :param seg_owner, agent_owner: as in :func:`cast` (an agent skips its own segments).
        """
        ang = np.ascontiguousarray(angles, np.float64)
        step, full = _uniform(ang)
        so = np.full(self.starts.shape[0], -1, np.int64) if seg_owner is None else \
            np.asarray(seg_owner, np.int64)
        ao = np.full(ang.shape[0], -2, np.int64) if agent_owner is None else \
            np.asarray(agent_owner, np.int64)
        out = _cast_grid(np.ascontiguousarray(origins, np.float64), ang, step > 0.0, step, full,
                         float(max_range), self.starts, self.ends, so, ao, self.x0, self.y0,
                         self.cell, self.nx, self.ny, self.offsets, self.items)
        return np.minimum(out, max_range)
