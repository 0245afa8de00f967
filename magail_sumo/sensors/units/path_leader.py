"""Path leader: the nearest road user in the agent's lane corridor ahead along its reference
path (appended with ``ObservationConfig.path_leader``).

The :mod:`~magail_sumo.sensors.units.leader` sensor looks straight ahead along the agent's
heading: on a bend or through a junction turn it misses the road user ahead on the agent's
lanes and sees one in the next lane. A route-following agent knows its path
(:mod:`magail_sumo.sim.paths`: in a city its SUMO route's lane centrelines through the
junctions, in a recording its recorded route), so this sensor looks along it. A road user is in
the agent's path when its box centre, projected on the path ahead (the nearest of the points
from the agent's progress point to ``leader_range`` + 10 m on), lies ``s_o`` m along the path
beyond the agent's progress ``s`` and within

    |lateral offset| < w_agent/2 + |sin Δ|·l_o/2 + |cos Δ|·w_o/2

of it (``Δ``: the other's heading less the path's there, so a vehicle standing across the path
blocks it with its length); an oncoming road user (``|Δ|`` > 135°) driving at
:data:`STANDING` m/s or more counts with its width only, ``w_agent/2 + w_o/2``: it is in the
path when head-on, not when it passes beside. Two agents standing in each other's path
(opposing left turners inside a junction, or a car that stopped for a crossing road user with
its nose in that road user's lane: their boxes reach into each other's corridor) would each
wait for the other for ever: of such a pair the one that can move :data:`TRIAL_MOVE` m along
its heading without its box reaching deeper into the other's (where two lanes merge inside a
junction, the one angled in ahead: the other would drive into its side), else the one with the
larger gap (more room; the higher box row on a tie) does not see the other, so it moves on, and
the other once it has gone.
``path_leader_gap`` (m) is ``s_o − s − l_agent/2 − (|cos Δ|·l_o/2 + |sin Δ|·w_o/2)``
(bumper to bumper along the path; negative when they overlap), ``path_leader_closing`` (m/s)
the agent's speed less the other's speed along the path there (> 0: the gap shrinks); of those
within ``leader_range``, the nearest. Without one: ``leader_range``, 0. An agent without a
reference path (free steering) reads the straight-ahead
:func:`~magail_sumo.sensors.units.leader.nearest_ahead` leader instead, and one with less than
``leader_range`` of its path left the nearer of the two (past its path's end route-relative
control drives on along the last heading: a recorded route ends where its log does). One numba
kernel over the agent × road-user pairs within reach (in a batched env only the agent's own
world's road users and the shared ones).
"""

from __future__ import annotations

import numba
import numpy as np

from ..base import SensorInput, register
from ..worlds import BoxGroups
from .leader import Leader, nearest_ahead

#: metres of path beyond ``leader_range`` searched for the projection of a road user's centre
PAST_RANGE = 10.0
#: cos of the heading difference below which a road user is oncoming (135°)
ONCOMING = -0.7071
#: speed (m/s) below which an oncoming road user is standing (it blocks with its length)
STANDING = 1.0
#: metres a standing agent of a pair in each other's path is moved, as a trial, to see whether
#: it can go without touching the other
TRIAL_MOVE = 1.0


@register
class PathLeader(Leader):
    """``path_leader_gap`` (m), ``path_leader_closing`` (m/s) (module doc; the leader's
    bounds and reading, found along the path)."""

    name = "path_leader"

    def find(self, inp: SensorInput, rng: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        path = inp.ego.path
        if path is None:
            return super().find(inp, rng)
        return along_path(inp.boxes, inp.index, path, rng)


def along_path(b, index: np.ndarray, path, rng: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each agent's path leader among boxes ``b`` (module doc): (A,) gap (m; ``inf`` without
    one), the leader's speed along the path there (m/s; 0 without one) and whether it has one.

    :param index: (A,) the agents' own rows of ``b``.
    :param path: :class:`~magail_sumo.sensors.base.PathAhead` of the agents (a row of -1:
        no path; that agent reads the straight-ahead leader).
    """
    n, a = len(b), len(index)
    if a == 0 or n <= 1:
        return np.full(a, np.inf), np.zeros(a), np.zeros(a, bool)
    f = lambda v: np.ascontiguousarray(v, np.float64)  # noqa: E731
    g = b.groups if b.groups is not None else BoxGroups.single(n)
    speed = np.zeros(n) if b.speed is None else f(b.speed)
    p = path.paths
    rows = np.ascontiguousarray(path.rows, np.int64)
    gap, along, found, freed = _along_path(
        f(b.x), f(b.y), f(b.yaw), f(b.length), f(b.width), speed,
        np.ascontiguousarray(index, np.int64), p.x, p.y, p.s, p.start, p.count, rows,
        np.ascontiguousarray(path.at, np.int64), f(path.s), float(rng), float(p.spacing),
        g.world, g.offsets, g.rows)
    # no reference path, or less than the range of it left: (also) straight ahead, the path
    # running on along its last heading as route-relative control drives it
    left = np.full(a, -np.inf)
    has = rows >= 0
    left[has] = p.length(rows[has]) - np.asarray(path.s, np.float64)[has]
    short = (~has | (left < rng)) & ~freed
    if short.any():
        idx = np.asarray(index, np.int64)[short]
        g2, a2, f2 = nearest_ahead(b, idx, np.asarray(b.x, np.float64)[idx],
                                   np.asarray(b.y, np.float64)[idx],
                                   np.asarray(b.yaw, np.float64)[idx], rng)
        use = f2 & (~found[short] | (g2 < gap[short]))
        sel = np.flatnonzero(short)[use]
        gap[sel], along[sel], found[sel] = g2[use], a2[use], True
    return gap, along, found


@numba.njit(cache=True)
def _along_path(bx, by, byaw, blen, bwid, bspeed, index, px, py, ps, start, count, prow, pat,
                s_ego, rng, spacing, world, offsets, rows):
    """:func:`along_path` for agents with a path (rows ``prow`` >= 0), and which of them a
    standing pair's release freed; ties go to the lowest box row."""
    a = index.shape[0]
    gap_out, along_out = np.full(a, np.inf), np.zeros(a)
    found = np.zeros(a, np.bool_)
    lead = np.full(a, -1, np.int64)
    shared = offsets.shape[0] - 2
    reach = rng + PAST_RANGE
    for i in range(a):
        r = prow[i]
        if r < 0:
            continue
        me = index[i]
        lo = start[r] + min(max(pat[i], 0), count[r] - 1)
        hi = min(start[r] + count[r], lo + int(reach / spacing) + 2)
        if hi - lo < 2:
            continue
        ex, ey = bx[me], by[me]
        best, bj, best_along = np.inf, -1, 0.0
        for bucket in (world[me], shared):
            for m in range(offsets[bucket], offsets[bucket + 1]):
                j = rows[m]
                if j == me:
                    continue
                if (bx[j] - ex) ** 2 + (by[j] - ey) ** 2 > (reach + blen[j]) ** 2:
                    continue
                # nearest path point ahead to the box centre
                kb, db = -1, np.inf
                for k in range(lo, hi):
                    d2 = (px[k] - bx[j]) ** 2 + (py[k] - by[j]) ** 2
                    if d2 < db:
                        db, kb = d2, k
                k2 = kb + 1 if kb + 1 < hi else kb
                k1 = k2 - 1
                tx, ty = px[k2] - px[k1], py[k2] - py[k1]
                tn = np.sqrt(tx * tx + ty * ty)
                if tn <= 0.0:
                    continue
                tx, ty = tx / tn, ty / tn
                dx, dy = bx[j] - px[kb], by[j] - py[kb]
                lon = dx * tx + dy * ty
                lat = -dx * ty + dy * tx
                s_o = ps[kb] + lon
                if not s_o > s_ego[i]:
                    continue
                d = byaw[j] - np.arctan2(ty, tx)
                cd, sd = abs(np.cos(d)), abs(np.sin(d))
                across = 0.5 * (sd * blen[j] + cd * bwid[j])
                if np.cos(d) < ONCOMING and abs(bspeed[j]) >= STANDING:
                    across = 0.5 * bwid[j]  # passing beside, or head-on: its width only
                if not abs(lat) < 0.5 * bwid[me] + across:
                    continue
                gap = s_o - s_ego[i] - 0.5 * blen[me] - 0.5 * (cd * blen[j] + sd * bwid[j])
                if gap < rng and (gap < best or (gap == best and j < bj)):
                    best, bj, best_along = gap, j, bspeed[j] * np.cos(d)
        if bj >= 0:
            found[i] = True
            gap_out[i] = best
            along_out[i] = best_along
            lead[i] = bj
    # two standing agents in each other's path: the one with more room goes first
    agent_of = np.full(bx.shape[0], -1, np.int64)
    for i in range(a):
        agent_of[index[i]] = i
    free = np.zeros(a, np.bool_)
    for i in range(a):
        j = lead[i]
        if j < 0 or agent_of[j] < 0:
            continue
        k = agent_of[j]
        me = index[i]
        if lead[k] != me or abs(bspeed[me]) >= STANDING or abs(bspeed[j]) >= STANDING:
            continue
        clear_i = _depth(bx, by, byaw, blen, bwid, me, j, TRIAL_MOVE) <= \
            _depth(bx, by, byaw, blen, bwid, me, j, 0.0)
        clear_k = _depth(bx, by, byaw, blen, bwid, j, me, TRIAL_MOVE) <= \
            _depth(bx, by, byaw, blen, bwid, j, me, 0.0)
        if clear_i != clear_k:
            free[i] = clear_i
        elif gap_out[i] > gap_out[k] or (gap_out[i] == gap_out[k] and me > j):
            free[i] = True
    for i in range(a):
        if free[i]:
            found[i] = False
            gap_out[i] = np.inf
            along_out[i] = 0.0
    return gap_out, along_out, found, free


@numba.njit(cache=True)
def _depth(bx, by, byaw, blen, bwid, i, j, move):
    """How deep (m) box ``i`` moved ``move`` m along its heading reaches into box ``j``: the
    least overlap over the separating axes of the two rectangles; 0 when they are apart."""
    ci, si = np.cos(byaw[i]), np.sin(byaw[i])
    cj, sj = np.cos(byaw[j]), np.sin(byaw[j])
    dx = bx[j] - (bx[i] + move * ci)
    dy = by[j] - (by[i] + move * si)
    depth = np.inf
    for ax, ay in ((ci, si), (-si, ci), (cj, sj), (-sj, cj)):
        ri = 0.5 * blen[i] * abs(ci * ax + si * ay) + 0.5 * bwid[i] * abs(-si * ax + ci * ay)
        rj = 0.5 * blen[j] * abs(cj * ax + sj * ay) + 0.5 * bwid[j] * abs(-sj * ax + cj * ay)
        depth = min(depth, ri + rj - abs(dx * ax + dy * ay))
    return max(depth, 0.0)
