"""Route-relative control: the steering that keeps a bicycle on its reference path, and the
``accel_offset`` action layout built on it.

In the ``accel_offset`` layout (:data:`~magail_sumo.sim.dynamics.ACTION_LAYOUTS`) a policy
chooses the longitudinal acceleration and a lateral offset ``d`` (m, positive = left of the
path; ``max_offset`` of :class:`~magail_sumo.sim.dynamics.BicycleLimits` at ±1) from its
reference path (:class:`~magail_sumo.sim.paths.Paths`: in a city the lane centrelines of its
SUMO route through the junctions' internal lanes; in a recorded scene its recorded route). The
steering is pure pursuit towards the goal point: the point of the path ``L`` m ahead of the
vehicle's progress point (past the path's end, on along its last heading: a vehicle that
overshoots its route's end drives on rather than turning back), moved ``d`` m along the path's
left normal there, with look-ahead

    L = max(min_lookahead, lookahead_time·|speed|)

and, with ``α`` the goal's bearing in the ego frame and ``ℓ`` its distance,

    steer = atan(2·wheelbase·sin(α) / ℓ)      (clipped to ±max_steer)

which puts the vehicle on the arc through the goal (the box centre stands in for the rear
axle). The vehicle then moves by the bicycle model (:func:`~magail_sumo.sim.dynamics.step`),
so its motion keeps the kinematics of free steering; a zero lateral action follows the path's
centreline, so staying on the route's lanes and turning onto the right lane at a junction is
structural, not learned. Vehicles in this layout do not reverse: the acceleration is raised to
at least ``-speed / dt``.
"""

from __future__ import annotations

import numba
import numpy as np

from .dynamics import WHEELBASE_RATIO, BicycleLimits, VehicleState, wrap_angle
from .paths import WINDOW, Paths

#: pure-pursuit look-ahead: seconds of travel at the current speed, and the least distance (m)
LOOKAHEAD_TIME = 0.8
MIN_LOOKAHEAD = 4.0


def pursuit_steer(state: VehicleState, wheelbase: np.ndarray, gx: np.ndarray, gy: np.ndarray,
                  max_steer: float) -> np.ndarray:
    """(A,) front-wheel angle (rad) of the arc from each vehicle's pose through goal (gx, gy)
    (m, scene frame), clipped to ±``max_steer``; 0 for a goal on the vehicle."""
    dx, dy = gx - state.x, gy - state.y
    dist = np.hypot(dx, dy)
    alpha = wrap_angle(np.arctan2(dy, dx) - state.yaw)
    k = np.where(dist > 1e-6, 2.0 * np.sin(alpha) / np.where(dist > 1e-6, dist, 1.0), 0.0)
    return np.clip(np.arctan(k * wheelbase), -max_steer, max_steer)


def follow(paths: Paths, rows: np.ndarray, hint: np.ndarray, state: VehicleState,
           wheelbase: np.ndarray, offset: np.ndarray, limits: BicycleLimits
           ) -> tuple[np.ndarray, np.ndarray]:
    """Steering of vehicles in ``state`` following paths ``rows`` at lateral ``offset`` (m,
    left positive; module doc), and their new progress hints ((A,) point indices).

    :param hint: (A,) progress indices from the last call (the projection's window).
    """
    at, s = paths.project(rows, state.x, state.y, hint)
    look = np.maximum(MIN_LOOKAHEAD, LOOKAHEAD_TIME * np.abs(state.speed))
    px, py, heading = paths.at(rows, s + look, extend=True)
    gx = px - np.sin(heading) * offset
    gy = py + np.cos(heading) * offset
    return pursuit_steer(state, wheelbase, gx, gy, limits.max_steer), at


def no_reverse(accel: np.ndarray, speed: np.ndarray, dt: float) -> np.ndarray:
    """``accel`` raised so that one step does not take the speed below 0."""
    return np.maximum(accel, -np.maximum(speed, 0.0) / dt)


def trial(points: np.ndarray, s0: float, s1: float, length: float, limits: BicycleLimits,
          speed: float = 2.5, dt: float = 0.1) -> VehicleState:
    """Poses of a vehicle of box ``length`` (m) following polyline ``points`` ((M, 2), m) at
    zero offset and a constant ``speed`` (m/s), from arc length ``s0`` (on the path, heading
    along it) until its progress reaches ``s1`` (m) or it has driven twice that far: the
    (T,) states of every ``dt``-s step, what route-relative control would make of that
    stretch (e.g. whether a turn tighter than the vehicle can make keeps it on the road)."""
    return trials([points], [s0], [s1], [length], limits, speed, dt)[0]


def trials(points, s0, s1, length, limits: BicycleLimits, speed: float = 2.5, dt: float = 0.1
           ) -> list[VehicleState]:
    """:func:`trial` of several vehicles at once (``points``: a polyline each; ``s0``, ``s1``,
    ``length``: one value each): each one's poses are those of its own :func:`trial` (every
    operation is per vehicle).

    One compiled loop (:func:`_crawl`) restates, per vehicle and in scalars, what
    :func:`follow` at zero offset and :func:`~magail_sumo.sim.dynamics.step` do over arrays:
    the steps of a crawl are sequential, and about 100 of them as array calls on a few
    elements cost about 17 ms a batch (the city's tight-turn test of each joining vehicle,
    12 % of a city worker's step in training), the compiled loop well under 1 ms. Its poses
    agree with the array functions' to about 1e-12 m (their ``tan`` / ``arctan`` /
    ``arctan2`` round the last bit differently; ``tests/test_path_leader.py``)."""
    n = len(points)
    if n == 0:
        return []
    paths = Paths.of(list(points))
    s0 = np.asarray(s0, np.float64).reshape(n)
    s1 = np.asarray(s1, np.float64).reshape(n)
    wheelbase = WHEELBASE_RATIO * np.asarray(length, np.float64).reshape(n)
    steps = np.ceil(2.0 * np.maximum(s1 - s0, 0.0) / (speed * dt)).astype(np.int64) + 1
    offsets = np.r_[0, np.cumsum(steps + 1)].astype(np.int64)
    poses = np.empty((int(offsets[-1]), 4))
    used = _crawl(paths.x, paths.y, paths.s, paths.start[:n], paths.count[:n], paths.spacing,
                  s0, s1, wheelbase, steps, offsets, float(speed), float(dt),
                  float(limits.max_accel), float(limits.max_brake), float(limits.max_steer),
                  float(limits.max_speed), float(limits.max_reverse_speed),
                  WINDOW[0], WINDOW[1], MIN_LOOKAHEAD, LOOKAHEAD_TIME, poses)
    return [VehicleState(*(poses[offsets[k]:offsets[k] + used[k], c].copy() for c in range(4)))
            for k in range(n)]


@numba.njit(cache=True)
def _wrap(a):
    return (a + np.pi) % (2.0 * np.pi) - np.pi


@numba.njit(cache=True)
def _at(x, y, s, base, cnt, d, extend):
    """:meth:`Paths.at` of one path (points ``base .. base + cnt - 1``) at arc length ``d``."""
    step = s[base + cnt - 1] / max(cnt - 1, 1)
    u = max(d / (step if step > 0 else 1.0), 0.0)
    j = min(np.int64(np.floor(u)), max(cnt - 2, 0))
    a, b = base + j, base + min(j + 1, cnt - 1)
    seg = s[b] - s[a]
    frac = max((d - s[a]) / seg if seg > 0 else 0.0, 0.0)
    if not extend:
        frac = min(frac, 1.0)
    return (x[a] + frac * (x[b] - x[a]), y[a] + frac * (y[b] - y[a]),
            np.arctan2(y[b] - y[a], x[b] - x[a]))


@numba.njit(cache=True)
def _project(x, y, s, base, cnt, px, py, hint, back, ahead):
    """:meth:`Paths.project` of one position on one path, searching around ``hint``."""
    lo = max(hint - back, 0)
    best, at = np.inf, lo
    for i in range(lo, min(lo + back + ahead + 1, cnt)):
        d2 = (x[base + i] - px) ** 2 + (y[base + i] - py) ** 2
        if d2 < best:
            best, at = d2, i
    foot_s = s[base + at]  # the nearer foot on the segments before and after point ``at``
    foot_d = np.hypot(x[base + at] - px, y[base + at] - py)
    for lo in (at - 1, at):
        if lo < 0 or lo + 1 >= cnt:
            continue
        a, b = base + lo, base + lo + 1
        ex, ey = x[b] - x[a], y[b] - y[a]
        ll = ex * ex + ey * ey
        u = max(((px - x[a]) * ex + (py - y[a]) * ey) / (ll if ll > 0 else 1.0), 0.0)
        if lo + 2 < cnt:  # the last segment: on past the path's end (Paths._foot)
            u = min(u, 1.0)
        d = np.hypot(x[a] + u * ex - px, y[a] + u * ey - py)
        if d < foot_d:
            foot_d, foot_s = d, s[a] + u * np.sqrt(ll)
    return at, foot_s


@numba.njit(cache=True)
def _crawl(x, y, s, start, count, spacing, s0, s1, wheelbase, steps, offsets, speed, dt,
           max_accel, max_brake, max_steer, max_speed, max_reverse, back, ahead, min_look,
           look_time, out):
    """The crawls of :func:`trials`: vehicle ``k``'s poses (x, y, yaw, speed) in rows
    ``offsets[k]`` on of ``out``; the number of poses of each."""
    n = start.size
    used = np.zeros(n, np.int64)
    accel = min(max(0.0, -max_brake), max_accel)
    for k in range(n):
        base, cnt, row = start[k], count[k], offsets[k]
        first = max(s0[k], 0.0)
        px, py, yaw = _at(x, y, s, base, cnt, first, False)
        v = speed
        out[row, 0], out[row, 1], out[row, 2], out[row, 3] = px, py, yaw, v
        m = 1
        at, prog = _project(x, y, s, base, cnt, px, py, np.int64(np.rint(first / spacing)),
                            back, ahead)
        for _ in range(steps[k]):
            gx, gy, _h = _at(x, y, s, base, cnt, prog + max(min_look, look_time * abs(v)), True)
            dx, dy = gx - px, gy - py
            dist = np.hypot(dx, dy)
            alpha = _wrap(np.arctan2(dy, dx) - yaw)
            curv = 2.0 * np.sin(alpha) / dist if dist > 1e-6 else 0.0
            steer = min(max(np.arctan(curv * wheelbase[k]), -max_steer), max_steer)
            v = min(max(v + accel * dt, -max_reverse), max_speed)
            d = v * dt
            kk = np.tan(steer) / wheelbase[k]
            mid = yaw + 0.5 * kk * d
            px, py, yaw = px + d * np.cos(mid), py + d * np.sin(mid), _wrap(yaw + kk * d)
            out[row + m, 0], out[row + m, 1], out[row + m, 2], out[row + m, 3] = px, py, yaw, v
            m += 1
            at, prog = _project(x, y, s, base, cnt, px, py, at, back, ahead)
            if prog >= s1[k]:
                break
        used[k] = m
    return used
