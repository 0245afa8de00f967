"""Interaction features: distance to the nearest object, collision and time to collision.

Every function works on batched float32 arrays ``(B, A, T)`` (batch × objects × steps; the
first ``n_eval`` objects are the evaluated ones) and returns ``(B, n_eval, T)``. Geometry is 2-D
in the scene frame (metres, headings radians CCW from +x).
"""

from __future__ import annotations

import numpy as np

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


def _rect_vertex_distance(px: np.ndarray, py: np.ndarray, cx: np.ndarray, cy: np.ndarray,
                          c: np.ndarray, s: np.ndarray, hl: np.ndarray, hw: np.ndarray
                          ) -> np.ndarray:
    """Distance from points to rectangles (0 inside); points carry a trailing axis of 4."""
    dx, dy = px - cx[..., None], py - cy[..., None]
    u = np.abs(c[..., None] * dx + s[..., None] * dy) - hl[..., None]
    v = np.abs(-s[..., None] * dx + c[..., None] * dy) - hw[..., None]
    u, v = np.maximum(u, 0), np.maximum(v, 0)
    return np.sqrt(u * u + v * v).min(-1)


_SIGNS = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], np.float32)  # CCW corners


def box_corners(x: np.ndarray, y: np.ndarray, heading: np.ndarray, length: np.ndarray,
                width: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corner coordinates ``(..., 4)`` each for x and y, counter-clockwise from front-left."""
    c, s = np.cos(heading)[..., None], np.sin(heading)[..., None]
    lx = _SIGNS[:, 0] * (length[..., None] / 2)
    ly = _SIGNS[:, 1] * (width[..., None] / 2)
    return x[..., None] + c * lx - s * ly, y[..., None] + s * lx + c * ly


def signed_box_distance(xa, ya, ha, la, wa, xb, yb, hb, lb, wb) -> np.ndarray:
    """Signed distance between rectangles A and B (broadcast arrays): the gap when apart,
    minus the penetration depth (smallest overlap over the four edge axes) when overlapping."""
    ca, sa, cb, sb = np.cos(ha), np.sin(ha), np.cos(hb), np.sin(hb)
    hla, hwa, hlb, hwb = la / 2, wa / 2, lb / 2, wb / 2
    dx, dy = xb - xa, yb - ya
    # separating-axis overlaps on A's and B's axes
    cab = np.abs(ca * cb + sa * sb)  # |cos(hb - ha)|
    sab = np.abs(sa * cb - ca * sb)  # |sin(hb - ha)|
    pen = np.minimum.reduce([
        hla + hlb * cab + hwb * sab - np.abs(ca * dx + sa * dy),
        hwa + hlb * sab + hwb * cab - np.abs(-sa * dx + ca * dy),
        hlb + hla * cab + hwa * sab - np.abs(cb * dx + sb * dy),
        hwb + hla * sab + hwa * cab - np.abs(-sb * dx + cb * dy),
    ])
    # gap: nearest vertex of one rectangle to the other
    axs, ays = box_corners(xa, ya, ha, la, wa)
    bxs, bys = box_corners(xb, yb, hb, lb, wb)
    gap = np.minimum(_rect_vertex_distance(axs, ays, xb, yb, cb, sb, hlb, hwb),
                     _rect_vertex_distance(bxs, bys, xa, ya, ca, sa, hla, hwa))
    return np.where(pen > 0, -pen, gap)


def distance_to_nearest_object(x, y, heading, length, width, valid, n_eval: int) -> np.ndarray:
    """Signed distance (m) from each evaluated object's rounded box to the nearest other valid
    object's rounded box; 1e10 when there is none or the object itself is invalid.

    :param x, y, heading: (B, A, T) float32.
    :param length, width: (A, T) float32.
    :param valid: (B, A, T) bool.
    :returns: (B, n_eval, T) float32.
    """
    f = np.float32
    r = np.minimum(length, width) * f(CORNER_ROUNDING_FACTOR / 2)
    cl, cw = length - 2 * r, width - 2 * r
    e = slice(0, n_eval)
    d = signed_box_distance(
        x[:, e, None], y[:, e, None], heading[:, e, None], cl[None, e, None], cw[None, e, None],
        x[:, None], y[:, None], heading[:, None], cl[None, None], cw[None, None])
    d = d - r[None, e, None] - r[None, None]
    ok = valid[:, e, None] & valid[:, None]
    ok[:, np.arange(n_eval), np.arange(n_eval)] = False
    return np.where(ok, d, f(EXTREMELY_LARGE_DISTANCE)).min(2)


def time_to_collision(x, y, heading, length, width, valid, speed, n_eval: int) -> np.ndarray:
    """Time (s) until each evaluated object reaches the nearest valid object it follows, at the
    current speed difference; capped at 5 s (also 5 s when nothing is followed or the gap does
    not close).

    An object is followed when it is ahead (longitudinal gap > 0 in the ego's frame), its
    heading differs by at most 75° (plain absolute difference, not wrapped) and it overlaps the
    ego's lane laterally (by more than 0.5 m, or at all when the headings differ by ≤ 10°).

    :param speed: (B, A, T) 2-D speed (m/s) of every object.
    :returns: (B, n_eval, T) float32.
    """
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
