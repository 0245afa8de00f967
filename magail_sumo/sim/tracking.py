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

import numpy as np

from .dynamics import WHEELBASE_RATIO, BicycleLimits, VehicleState, step, wrap_angle
from .paths import Paths

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
    return steer_from(paths, rows, s, state, wheelbase, offset, limits), at


def steer_from(paths: Paths, rows: np.ndarray, s: np.ndarray, state: VehicleState,
               wheelbase: np.ndarray, offset: np.ndarray, limits: BicycleLimits) -> np.ndarray:
    """:func:`follow`'s steering of vehicles whose progress on their paths is ``s`` ((A,) arc
    length, m, as :meth:`~magail_sumo.sim.paths.Paths.project` gives it)."""
    look = np.maximum(MIN_LOOKAHEAD, LOOKAHEAD_TIME * np.abs(state.speed))
    px, py, heading = paths.at(rows, s + look, extend=True)
    gx = px - np.sin(heading) * offset
    gy = py + np.cos(heading) * offset
    return pursuit_steer(state, wheelbase, gx, gy, limits.max_steer)


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
    ``length``: one value each), stepped together: each one's poses are those of its own
    :func:`trial` (every operation is per vehicle), for one loop over the steps."""
    n = len(points)
    if n == 0:
        return []
    paths = Paths.of(list(points))
    rows = np.arange(n, dtype=np.int64)
    s0 = np.asarray(s0, np.float64)
    s1 = np.asarray(s1, np.float64)
    first = np.maximum(s0, 0.0)
    x, y, yaw = paths.at(rows, first)
    state = VehicleState(x, y, yaw, np.full(n, float(speed)))
    wheelbase = WHEELBASE_RATIO * np.asarray(length, np.float64)
    hint = np.round(first / paths.spacing).astype(np.int64)  # not a later pass nearby
    steps = np.ceil(2.0 * np.maximum(s1 - s0, 0.0) / (speed * dt)).astype(np.int64) + 1
    out = [[(state.x[k], state.y[k], state.yaw[k], state.speed[k])] for k in range(n)]
    # the progress of each state is projected once: the stop test's projection is the next
    # step's (the same state and hint as follow would project)
    at, s = paths.project(rows, state.x, state.y, hint)
    live = np.ones(n, bool)
    for i in range(int(steps.max())):
        live &= i < steps
        r = np.flatnonzero(live)
        if r.size == 0:
            break
        cur = VehicleState(state.x[r], state.y[r], state.yaw[r], state.speed[r])
        zero = np.zeros(r.size)
        steer = steer_from(paths, rows[r], s[r], cur, wheelbase[r], zero, limits)
        new = step(cur, zero, steer, wheelbase[r], dt, limits)
        for j, k in enumerate(r.tolist()):
            out[k].append((new.x[j], new.y[j], new.yaw[j], new.speed[j]))
        state.x[r], state.y[r], state.yaw[r], state.speed[r] = new.x, new.y, new.yaw, new.speed
        at[r], s[r] = paths.project(rows[r], new.x, new.y, at[r])
        live[r[s[r] >= s1[r]]] = False
    return [VehicleState(*(np.array(c, np.float64) for c in zip(*o))) for o in out]
