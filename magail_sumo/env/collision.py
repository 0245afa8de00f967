"""Oriented-box overlap tests (separating-axis theorem) over all agents of a step, numba.

Boxes are given by centre (m), yaw (rad) and size (m) in the scene frame. Two boxes overlap
when no edge normal of either box separates their projections (touching counts as overlap).
"""

from __future__ import annotations

import numba
import numpy as np

from magail_sumo.sensors.worlds import BoxGroups


@numba.njit(cache=True, inline="always")
def _separated(ax, ay, ac, as_, al, aw, bx, by, bc, bs, bl, bw):
    dx, dy = bx - ax, by - ay
    for k in range(4):
        if k == 0:
            nx, ny = ac, as_
        elif k == 1:
            nx, ny = -as_, ac
        elif k == 2:
            nx, ny = bc, bs
        else:
            nx, ny = -bs, bc
        ra = al * abs(ac * nx + as_ * ny) + aw * abs(-as_ * nx + ac * ny)
        rb = bl * abs(bc * nx + bs * ny) + bw * abs(-bs * nx + bc * ny)
        if abs(dx * nx + dy * ny) > ra + rb:
            return True
    return False


@numba.njit(cache=True)
def _first_overlap(x, y, yaw, half_l, half_w, query, world, offsets, rows):
    """Per query box, the lowest overlapping row among its world's boxes and the shared
    ones (:class:`~magail_sumo.sensors.worlds.BoxGroups` buckets), else -1."""
    out = np.full(query.shape[0], -1, np.int64)
    c, s = np.cos(yaw), np.sin(yaw)
    rad = np.sqrt(half_l * half_l + half_w * half_w)
    shared = offsets.shape[0] - 2
    for q in range(query.shape[0]):
        i = query[q]
        best = -1
        for bucket in (world[i], shared):
            for m in range(offsets[bucket], offsets[bucket + 1]):
                j = rows[m]  # ascending within a bucket: the first overlap is its lowest
                if j == i or (best >= 0 and j > best):
                    continue
                dx, dy = x[j] - x[i], y[j] - y[i]
                r = rad[i] + rad[j]
                if dx * dx + dy * dy > r * r:
                    continue
                if not _separated(x[i], y[i], c[i], s[i], half_l[i], half_w[i],
                                  x[j], y[j], c[j], s[j], half_l[j], half_w[j]):
                    best = j
                    break
        out[q] = best
    return out


def first_overlap(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray,
                  width: np.ndarray, query: np.ndarray, groups=None) -> np.ndarray:
    """For boxes at rows ``query``, the lowest row of another box overlapping it, else -1.

    :param x, y, yaw, length, width: (N,) boxes. :param query: (A,) rows to test.
    :param groups: the boxes' worlds (:class:`~magail_sumo.sensors.worlds.BoxGroups`): a box
        only meets its own world's boxes and the shared ones; None: every box meets every box.
    :returns: (A,) int64.
    """
    f = lambda v: np.ascontiguousarray(v, np.float64)  # noqa: E731
    g = groups if groups is not None else BoxGroups.single(len(x))
    return _first_overlap(f(x), f(y), f(yaw), 0.5 * f(length), 0.5 * f(width),
                          np.ascontiguousarray(query, np.int64), g.world, g.offsets, g.rows)
