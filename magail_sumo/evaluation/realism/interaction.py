"""Interaction features: distance to the nearest object, collision and time to collision.

Every function works on batched float32 arrays ``(B, A, T)`` (batch × objects × steps; the
first ``n_eval`` objects are the evaluated ones) and returns ``(B, n_eval, T)``. Geometry is 2-D
in the scene frame (metres, headings radians CCW from +x).
"""

from __future__ import annotations

import numba
import numpy as np

from magail_sumo.sim.boxes import signed_box_distance  # noqa: F401 (part of this API)

#: Boxes are rounded rectangles with corner radius ``min(length, width) * 0.7 / 2``.
CORNER_ROUNDING_FACTOR = 0.7
#: Fill value for pairs that do not count (metres).
EXTREMELY_LARGE_DISTANCE = 1e10
#: Distance below which two boxes collide (strict inequality), metres.
COLLISION_DISTANCE_THRESHOLD = 0.0
#: Time-to-collision cap and value when nothing is followed, seconds.
MAX_TTC_SEC = 5.0
MAX_HEADING_DIFF = np.radians(75.0)
MAX_HEADING_DIFF_SMALL_OVERLAP = np.radians(10.0)
SMALL_OVERLAP_THRESHOLD = 0.5


@numba.njit(cache=True, inline="always")
def _vertex_distance(xa, ya, ca, sa, hla, hwa, xb, yb, cb, sb, hlb, hwb):  # pragma: no cover
    """Smallest distance from A's corners to rectangle B (the float32 operations, in order, of
    :func:`~magail_sumo.sim.boxes.box_corners` and
    :func:`~magail_sumo.sim.boxes.rect_vertex_distance`)."""
    z = np.float32(0.0)
    best = np.float32(np.inf)
    for k in range(4):
        lx = hla if k == 0 or k == 3 else -hla
        ly = hwa if k < 2 else -hwa
        dx = xa + ca * lx - sa * ly - xb
        dy = ya + sa * lx + ca * ly - yb
        u = max(abs(cb * dx + sb * dy) - hlb, z)
        v = max(abs(-sb * dx + cb * dy) - hwb, z)
        best = min(best, np.sqrt(u * u + v * v))
    return best


@numba.njit(cache=True, inline="always")
def _box_distance(xa, ya, ca, sa, hla, hwa, xb, yb, cb, sb, hlb, hwb):  # pragma: no cover
    """:func:`signed_box_distance` of one pair of rectangles (same float32 operations)."""
    dx, dy = xb - xa, yb - ya
    cab = abs(ca * cb + sa * sb)
    sab = abs(sa * cb - ca * sb)
    pen = hla + hlb * cab + hwb * sab - abs(ca * dx + sa * dy)
    pen = min(pen, hwa + hlb * sab + hwb * cab - abs(-sa * dx + ca * dy))
    pen = min(pen, hlb + hla * cab + hwa * sab - abs(cb * dx + sb * dy))
    pen = min(pen, hwb + hla * sab + hwa * cab - abs(-sb * dx + cb * dy))
    if pen > 0:
        return -pen
    return min(_vertex_distance(xa, ya, ca, sa, hla, hwa, xb, yb, cb, sb, hlb, hwb),
               _vertex_distance(xb, yb, cb, sb, hlb, hwb, xa, ya, ca, sa, hla, hwa))


@numba.njit(cache=True, inline="always")
def _centre_distance_sq(x, y, b, i, j, t):  # pragma: no cover - numba
    dx = np.float64(x[b, j, t]) - np.float64(x[b, i, t])
    dy = np.float64(y[b, j, t]) - np.float64(y[b, i, t])
    return dx * dx + dy * dy


@numba.njit(cache=True, parallel=True)
def _nearest_object(x, y, c, s, hl, hw, r, bound, margin, valid, n_eval):  # pragma: no cover
    B, A, T = x.shape
    out = np.empty((B, n_eval, T), np.float32)
    fill = np.float32(EXTREMELY_LARGE_DISTANCE)
    for k in numba.prange(B * n_eval):
        b, i = k // n_eval, k % n_eval
        for t in range(T):
            best = fill
            if valid[b, i, t]:
                # broad phase: the nearest centre seeds the minimum; any other object whose
                # bounding circle lies farther than it (plus the margin) cannot be nearer
                seed, seed_d2 = -1, np.inf
                for j in range(A):
                    if j != i and valid[b, j, t]:
                        d2 = _centre_distance_sq(x, y, b, i, j, t)
                        if d2 < seed_d2:
                            seed, seed_d2 = j, d2
                for j in range(A):
                    if j == i or not valid[b, j, t]:
                        continue
                    if j != seed:
                        reach = max(np.float64(best), 0.0) + margin + bound[i, t] + bound[j, t]
                        if _centre_distance_sq(x, y, b, i, j, t) > reach * reach:
                            continue
                    d = _box_distance(x[b, i, t], y[b, i, t], c[b, i, t], s[b, i, t], hl[i, t],
                                      hw[i, t], x[b, j, t], y[b, j, t], c[b, j, t], s[b, j, t],
                                      hl[j, t], hw[j, t]) - r[i, t] - r[j, t]
                    if d < best:
                        best = d
            out[b, i, t] = best
    return out


def distance_to_nearest_object(x, y, heading, length, width, valid, n_eval: int) -> np.ndarray:
    """Signed distance (m) from each evaluated object's rounded box to the nearest other valid
    object's rounded box; 1e10 when there is none or the object itself is invalid.

    A numba kernel over (batch, evaluated object) with a bounding-circle broad phase: only the
    pairs whose circles can be nearer than the best pair so far get the exact distance, with
    the float32 operations of :func:`signed_box_distance` (the result is that of the all-pairs
    minimum, bit for bit).

    :param x, y, heading: (B, A, T) float32.
    :param length, width: (A, T) float32.
    :param valid: (B, A, T) bool.
    :returns: (B, n_eval, T) float32.
    """
    f = np.float32
    c32 = lambda a: np.ascontiguousarray(a, f)  # noqa: E731
    length, width, heading = c32(length), c32(width), c32(heading)
    r = np.minimum(length, width) * f(CORNER_ROUNDING_FACTOR / 2)
    cl, cw = length - 2 * r, width - 2 * r
    # the rounded box lies inside the full box, inside the circle of its half-diagonal
    # (no pruning next to a box of non-positive size: the argument does not hold)
    bound = np.sqrt(length.astype(np.float64) ** 2 + width.astype(np.float64) ** 2) / 2
    bound = np.where((length > 0) & (width > 0), bound, np.inf)
    x, y = c32(x), c32(y)
    # float32 rounding of the exact distances: 1 m plus 32 ulps of the largest coordinate
    mag = max(float(np.abs(x).max(initial=0.0)), float(np.abs(y).max(initial=0.0)))
    margin = 1.0 + 4e-6 * mag if np.isfinite(mag) else np.inf
    return _nearest_object(x, y, np.cos(heading), np.sin(heading), cl / 2, cw / 2, r, bound,
                           margin, np.ascontiguousarray(valid, np.bool_), int(n_eval))


@numba.njit(cache=True)
def _ttc_candidates(x, y, heading, ce, se, length, width, reach, valid, n_eval, cand_key,
                    cand_j, cand_yaw):  # pragma: no cover - numba
    """The (b, i, t) key, object j and heading difference of every pair that can be followed
    (see :func:`time_to_collision`); only counts them when ``cand_key`` is empty."""
    B, A, T = x.shape
    fill = cand_key.shape[0] > 0
    n = 0
    max_yaw = np.float32(MAX_HEADING_DIFF)
    two = np.float32(2.0)
    for b in range(B):
        for i in range(n_eval):
            for t in range(T):
                for j in range(A):
                    if not valid[b, j, t]:
                        continue
                    yaw = abs(heading[b, j, t] - heading[b, i, t])
                    if not yaw <= max_yaw:
                        continue
                    dx, dy = x[b, j, t] - x[b, i, t], y[b, j, t] - y[b, i, t]
                    # followed needs long_dist = ahead - long_off > 0 with long_off >= 0, and
                    # lat_overlap = side - lat_off < 0 with lat_off <= j's half-diagonal
                    ahead = ce[b, i, t] * dx + se[b, i, t] * dy - length[i, t] / two
                    if not ahead > 0:
                        continue
                    side = abs(-se[b, i, t] * dx + ce[b, i, t] * dy) - width[i, t] / two
                    if not side < reach[j, t]:
                        continue
                    if fill:
                        cand_key[n] = (b * n_eval + i) * T + t
                        cand_j[n] = j
                        cand_yaw[n] = yaw
                    n += 1
    return n


@numba.njit(cache=True)
def _ttc_finish(x, y, ce, se, length, width, speed, n_eval, cand_key, cand_j, cand_yaw, c, s
                ):  # pragma: no cover - numba
    """TTC from the candidates (same float32 operations as the all-pairs version): the
    followed object with the smallest gap (the first of equal ones), else 5 s."""
    B, A, T = x.shape
    cap = np.float32(MAX_TTC_SEC)
    out = np.full((B, n_eval, T), cap, np.float32)
    best = np.full(B * n_eval * T, np.float32(np.inf), np.float32)
    best_j = np.full(B * n_eval * T, -1, np.int64)
    two = np.float32(2.0)
    small = np.float32(SMALL_OVERLAP_THRESHOLD)
    yaw_small = np.float32(MAX_HEADING_DIFF_SMALL_OVERLAP)
    for m in range(cand_key.shape[0]):
        key, j = cand_key[m], cand_j[m]
        t = key % T
        i = (key // T) % n_eval
        b = key // (T * n_eval)
        hl, hw = length[j, t] / two, width[j, t] / two
        long_off = hl * c[m] + hw * s[m]
        lat_off = hl * s[m] + hw * c[m]
        dx, dy = x[b, j, t] - x[b, i, t], y[b, j, t] - y[b, i, t]
        long_dist = ce[b, i, t] * dx + se[b, i, t] * dy - length[i, t] / two - long_off
        lat_overlap = abs(-se[b, i, t] * dx + ce[b, i, t] * dy) - width[i, t] / two - lat_off
        if (long_dist > 0 and lat_overlap < 0
                and (lat_overlap < -small or cand_yaw[m] <= yaw_small)
                and long_dist < best[key]):
            best[key] = long_dist
            best_j[key] = j
    for key in range(B * n_eval * T):
        j = best_j[key]
        if j >= 0:
            t = key % T
            i = (key // T) % n_eval
            b = key // (T * n_eval)
            rel = speed[b, i, t] - speed[b, j, t]
            if rel > 0:
                q = best[key] / rel
                out[b, i, t] = cap if q >= cap else q
    return out


#: Largest coordinate (m) and box size (m) for which :func:`time_to_collision` uses its
#: kernel: any followed gap is then far below the 1e10 added to the others.
_TTC_MAX_COORDINATE = 1e8
_TTC_MAX_SIZE = 1e4


def time_to_collision(x, y, heading, length, width, valid, speed, n_eval: int) -> np.ndarray:
    """Time (s) until each evaluated object reaches the nearest valid object it follows, at the
    current speed difference; capped at 5 s (also 5 s when nothing is followed or the gap does
    not close).

    An object is followed when it is ahead (longitudinal gap > 0 in the ego's frame), its
    heading differs by at most 75° (plain absolute difference, not wrapped) and it overlaps the
    ego's lane laterally (by more than 0.5 m, or at all when the headings differ by ≤ 10°).

    Numba kernels: the pairs that can be followed (ahead of the ego and within the other's
    half-diagonal of its lane) are found first, then only they get the exact test, with the
    float32 operations of :func:`time_to_collision_all_pairs` (bit for bit the same result;
    inputs beyond 1e8 m or sizes outside [0, 1e4] m go to that function).

    :param speed: (B, A, T) 2-D speed (m/s) of every object.
    :returns: (B, n_eval, T) float32.
    """
    f32 = lambda a: np.ascontiguousarray(a, np.float32)  # noqa: E731
    x, y, heading, length, width = f32(x), f32(y), f32(heading), f32(length), f32(width)
    big = max(float(np.abs(x).max(initial=0.0)), float(np.abs(y).max(initial=0.0)))
    if not (big <= _TTC_MAX_COORDINATE and bool((length >= 0).all()) and bool((width >= 0).all())
            and float(length.max(initial=0.0)) <= _TTC_MAX_SIZE
            and float(width.max(initial=0.0)) <= _TTC_MAX_SIZE):
        return time_to_collision_all_pairs(x, y, heading, length, width, valid, speed, n_eval)
    he = heading[:, :n_eval]
    ce, se = np.cos(he), np.sin(he)
    hd = np.sqrt(length.astype(np.float64) ** 2 + width.astype(np.float64) ** 2) / 2
    reach = hd * (1 + 1e-5) + 1e-6  # float32 rounding of lat_off
    valid = np.ascontiguousarray(valid, np.bool_)
    args = (x, y, heading, ce, se, length, width, reach, valid, int(n_eval))
    n = _ttc_candidates(*args, np.zeros(0, np.int64), np.zeros(0, np.int64),
                        np.zeros(0, np.float32))
    key, j, yaw = np.empty(n, np.int64), np.empty(n, np.int64), np.empty(n, np.float32)
    _ttc_candidates(*args, key, j, yaw)
    return _ttc_finish(x, y, ce, se, length, width, f32(speed), int(n_eval), key, j, yaw,
                       np.abs(np.cos(yaw)), np.abs(np.sin(yaw)))


def time_to_collision_all_pairs(x, y, heading, length, width, valid, speed, n_eval: int
                                ) -> np.ndarray:
    """:func:`time_to_collision` over all (evaluated, other) pairs in numpy (the reference)."""
    f = np.float32
    e = slice(0, n_eval)
    he = heading[:, e, None]
    yaw = np.abs(heading[:, None] - he)
    c, s = np.abs(np.cos(yaw)), np.abs(np.sin(yaw))
    hl, hw = length[None, None] / 2, width[None, None] / 2
    long_off = hl * c + hw * s
    lat_off = hl * s + hw * c
    dx = x[:, None] - x[:, e, None]
    dy = y[:, None] - y[:, e, None]
    ce, se = np.cos(he), np.sin(he)
    long_dist = ce * dx + se * dy - length[None, e, None] / 2 - long_off
    lat_overlap = np.abs(-se * dx + ce * dy) - width[None, e, None] / 2 - lat_off
    followed = ((long_dist > 0) & (yaw <= f(MAX_HEADING_DIFF)) & (lat_overlap < 0)
                & ((lat_overlap < -f(SMALL_OVERLAP_THRESHOLD))
                   | (yaw <= f(MAX_HEADING_DIFF_SMALL_OVERLAP))))
    masked = np.where(valid[:, None] & followed, long_dist,
                      long_dist + f(EXTREMELY_LARGE_DISTANCE))
    k = masked.argmin(2)  # (B, E, T)
    dist = np.take_along_axis(masked, k[:, :, None], 2)[:, :, 0]
    rel = speed[:, e] - np.take_along_axis(speed, k, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(rel > 0, np.minimum(dist / rel, f(MAX_TTC_SEC)), f(MAX_TTC_SEC))
