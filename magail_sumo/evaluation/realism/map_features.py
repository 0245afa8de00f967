"""Map features: signed distance from box corners to the road edges, and off-road.

The signed distance of a point is taken to the road-edge segment nearest in 3-D (with z
stretched ×3, so edges on other levels lose); it is the 2-D distance to that segment, negative
on the segment's left (on-road) side and positive on its right (off-road). Beyond a segment's
ends the sign is resolved with the neighbouring segment (max if the joint is convex, else min).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from magail_sumo.evaluation.realism.interaction import box_corners
from magail_sumo.scene import Scene

#: Vertical stretch applied when choosing the nearest segment.
Z_STRETCH = 3.0
#: Squared 3-D gap (m²) between first and last point below which a polyline is a ring.
CYCLIC_THRESHOLD_SQ = 1.0
#: Distance above which a box corner is off-road (strict), metres.
OFFROAD_DISTANCE_THRESHOLD = 0.0
#: Fill value for invalid object steps.
INVALID_DISTANCE = -1e10
_BLOCK = 16  # segments per bounding box in the nearest-segment search


@dataclass(frozen=True, eq=False)
class RoadEdgeSegments:
    """Road-edge segments of a scene, flattened in map order.

    :param a, b: (S, 3) float32 start and end points.
    :param prior, next: (S,) int64 neighbouring segment used beyond the start / end (-1: none).
    :param convex_prior, convex_next: (S,) bool, whether the joint with that neighbour turns
        left (positive 2-D cross product).
    :param block_lo, block_hi: (nb, 2) float32 xy bounds of each block of ``_BLOCK`` segments.
    """

    a: np.ndarray
    b: np.ndarray
    prior: np.ndarray
    next: np.ndarray
    convex_prior: np.ndarray
    convex_next: np.ndarray
    block_lo: np.ndarray
    block_hi: np.ndarray


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
    nb = -(-len(a) // _BLOCK)
    pad = nb * _BLOCK - len(a)
    lo = np.minimum(a[:, :2], b[:, :2])
    hi = np.maximum(a[:, :2], b[:, :2])
    lo = np.concatenate([lo, np.repeat(lo[-1:], pad, 0)]).reshape(nb, _BLOCK, 2).min(1)
    hi = np.concatenate([hi, np.repeat(hi[-1:], pad, 0)]).reshape(nb, _BLOCK, 2).max(1)
    return RoadEdgeSegments(a, b, prior, nxt, convex_prior, convex_next, lo, hi)


@numba.njit(cache=True, inline="always")
def _side(qx, qy, ax, ay, bx, by):  # pragma: no cover - numba
    c = (qx - ax) * (by - ay) - (qy - ay) * (bx - ax)
    return np.float32(1.0) if c > 0 else (np.float32(-1.0) if c < 0 else np.float32(0.0))


@numba.njit(cache=True, parallel=True)
def _signed_distance(q, a, b, prior, nxt, cvp, cvn, blo, bhi):  # pragma: no cover - numba
    n, S = q.shape[0], a.shape[0]
    nblk = blo.shape[0]
    out = np.empty(n, np.float32)
    zs = np.float32(Z_STRETCH)
    for i in numba.prange(n):
        qx, qy, qz = q[i, 0], q[i, 1], q[i, 2]
        best = np.float32(np.inf)
        bi = 0
        for k in range(nblk):
            gx = max(blo[k, 0] - qx, np.float32(0.0), qx - bhi[k, 0])
            gy = max(blo[k, 1] - qy, np.float32(0.0), qy - bhi[k, 1])
            if gx * gx + gy * gy > best:
                continue
            for s in range(k * _BLOCK, min(S, (k + 1) * _BLOCK)):
                dx, dy, dz = b[s, 0] - a[s, 0], b[s, 1] - a[s, 1], b[s, 2] - a[s, 2]
                px, py, pz = qx - a[s, 0], qy - a[s, 1], qz - a[s, 2]
                den = dx * dx + dy * dy
                t = (px * dx + py * dy) / den if den != 0 else np.float32(0.0)
                tc = min(max(t, np.float32(0.0)), np.float32(1.0))
                ox, oy, oz = px - dx * tc, py - dy * tc, (pz - dz * tc) * zs
                d3 = ox * ox + oy * oy + oz * oz
                if d3 < best:
                    best = d3
                    bi = s
        s = bi
        dx, dy = b[s, 0] - a[s, 0], b[s, 1] - a[s, 1]
        px, py = qx - a[s, 0], qy - a[s, 1]
        den = dx * dx + dy * dy
        t = (px * dx + py * dy) / den if den != 0 else np.float32(0.0)
        tc = min(max(t, np.float32(0.0)), np.float32(1.0))
        ox, oy = px - dx * tc, py - dy * tc
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
    """Signed 2-D distance (m, positive off-road) of (..., 3) float32 points."""
    q = np.ascontiguousarray(points, np.float32).reshape(-1, 3)
    out = _signed_distance(q, segs.a, segs.b, segs.prior, segs.next, segs.convex_prior,
                           segs.convex_next, segs.block_lo, segs.block_hi)
    return out.reshape(points.shape[:-1])


def distance_to_road_edge(x, y, z, heading, length, width, height, valid,
                          segs: RoadEdgeSegments) -> np.ndarray:
    """Signed distance (m) of each box's most off-road bottom corner; -1e10 where invalid.

    :param x, y, z, heading, valid: (B, E, T); ``length, width, height``: (E, T).
    """
    cx, cy = box_corners(x, y, heading, np.broadcast_to(length, x.shape),
                         np.broadcast_to(width, x.shape))
    cz = np.broadcast_to((z - height / 2)[..., None], cx.shape)
    d = signed_distance_to_road_edge(np.stack([cx, cy, cz], -1), segs).max(-1)
    return np.where(valid, d, np.float32(INVALID_DISTANCE))
