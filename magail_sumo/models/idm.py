"""The Intelligent Driver Model as a rule from observations to route-relative actions.

:class:`IdmRule` maps observation rows (``action_layout: accel_offset``) to normalised actions:
the IDM acceleration (Treiber, Hennecke & Helbing 2000) towards the road user ahead in the
agent's path (the ``path_leader`` observation when the rows have it: along the reference path,
:mod:`magail_sumo.sensors.units.path_leader`; else the straight-ahead ``leader``: gap ``s`` m,
closing speed ``Δv`` m/s) and a lateral offset of 0 (pure pursuit keeps the agent on its
route's lanes, :mod:`magail_sumo.sim.tracking`):

    a = a_max · [1 − (v / v0)^4 − (s* / s)^2],   s* = s0 + v·T + v·Δv / (2·sqrt(a_max·b))

(free road: no interaction term). The desired speed ``v0`` is the road's speed limit where
the observation has it (``speed_limit``, :mod:`magail_sumo.sensors.units.speed_limit`; times
``limit_factor``; ``v0`` where the limit is unknown), times the agent's own desired-speed
factor where the observation has it (``speed_factor``, :mod:`magail_sumo.sensors.units.
speed_factor`: in a city the factor SUMO drew for the vehicle, as SUMO's drivers drive the
limit times theirs), at most ``sqrt(v_low² + 2·b·d)`` before a
lower limit ``v_low`` ``d`` m ahead (it brakes comfortably down to it by its start). It is
lowered before bends: the route look-ahead (``route_points``) gives each point's curvature
``κ = 2·|y| / (x² + y²)`` (the arc from the car through it), and ``v0`` is at most
``sqrt(a_lat / κ)`` (lateral acceleration ``a_lat``). Before a red or yellow light (the
``light`` observation) whose stop line is ``light_gap`` m ahead
(:mod:`magail_sumo.sensors.units.light_gap`) it brakes to stop ``s0`` before the line,
``v² / (2·d)`` (at most ``max_brake``), keeping the IDM acceleration when that is lower. With
the give-way observation (``give_way``, :mod:`magail_sumo.sensors.units.give_way`) it accepts
the gap before a road user it must give way to only when it clears the conflict (``clear`` m
past its entry, accelerating at ``a_clear`` from ``v``) ``margin`` s before that road user
arrives; otherwise it stops ``s0`` before the conflict the same way. With the route's standing
end observed (``route_stop``, :mod:`magail_sumo.sensors.units.route_stop`: a recorded driver
who parks or halts where its route ends) it stops at that end the same way (a recorded scene;
a city has none). Pure array functions of
the observation, no memory: the same rule drives the ``idm`` baseline
(:mod:`magail_sumo.agents.idm`) and is the action prior a learned policy can
add a residual to (:mod:`magail_sumo.models.priors`).

Units: m, s, m/s, m/s²; actions normalised by :func:`magail_sumo.sim.dynamics.normalise`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magail_sumo.sensors.observation import ObservationConfig, observation_names
from magail_sumo.sensors.units.give_way import GIVE_WAY_RANGE
from magail_sumo.sensors.units.light_gap import LIGHT_RANGE
from magail_sumo.sensors.units.route_stop import ROUTE_STOP_RANGE
from magail_sumo.sim.dynamics import BicycleLimits, normalise

#: light codes of the ``light`` observation that stop an IDM driver (yellow, red)
STOP_LIGHTS = (2.0, 3.0)


@dataclass(frozen=True)
class IdmParams:
    """IDM parameters (urban defaults). A headway ``T`` of 1 s and ``a_max`` of 2 m/s²
    discharge a queue at a green light about as fast as SUMO's default drivers (20 cars past
    the line in 40 s, 15 with 1.5 s and 1.5 m/s², which cost the cologne8 city 19 of 382 trips
    in 10 min); gaps at junctions are still judged at 1.5 m/s² (``a_clear``).

    :param v0: desired speed (m/s) where the speed limit is unknown or not observed.
    :param limit_factor: the desired speed as a multiple of a known speed limit.
    :param T: time headway (s). :param s0: standstill gap (m).
    :param a_max: maximum acceleration (m/s²). :param b: comfortable deceleration (m/s²).
    :param a_clear: the acceleration (m/s²) a gap at a junction is judged by (how soon the
        agent clears the conflict): lower than ``a_max``, so a gap is taken with time to spare.
    :param max_brake: the hardest braking for a light (m/s²).
    :param a_lat: the lateral acceleration bends are taken at (m/s²).
    :param hold: within this many metres of the point where it stops for a light or a road
        user given way to, the rule brakes fully (m).
    :param clear: the length of a junction conflict to cross (m).
    :param margin: the time (s) a road user given way to must still be away when the agent
        has cleared the conflict.
    """

    v0: float = 13.9
    limit_factor: float = 1.0
    T: float = 1.0
    s0: float = 2.0
    a_max: float = 2.0
    b: float = 2.0
    a_clear: float = 1.5
    max_brake: float = 6.0
    a_lat: float = 2.0
    hold: float = 1.0
    clear: float = 8.0
    margin: float = 1.0


def idm_accel(v: np.ndarray, gap: np.ndarray, closing: np.ndarray, p: IdmParams,
              v0: np.ndarray | float | None = None) -> np.ndarray:
    """(A,) IDM acceleration (m/s²) at speeds ``v`` with leaders ``gap`` m ahead closing at
    ``closing`` m/s (``gap`` inf: free road), desired speed ``v0`` (default ``p.v0``)."""
    v0 = p.v0 if v0 is None else np.maximum(v0, 0.5)
    v = np.maximum(np.asarray(v, np.float64), 0.0)
    star = p.s0 + v * p.T + v * closing / (2.0 * np.sqrt(p.a_max * p.b))
    gap = np.maximum(np.asarray(gap, np.float64), 0.1)
    interact = np.where(np.isfinite(gap), (np.maximum(star, 0.0) / gap) ** 2, 0.0)
    return p.a_max * (1.0 - (v / v0) ** 4 - interact)


def desired_speed(limit: np.ndarray, low: np.ndarray, gap: np.ndarray, p: IdmParams
                  ) -> np.ndarray:
    """(A,) desired speed (m/s) under the speed limits: ``limit_factor`` times the limit
    here (``p.v0`` where 0, unknown), at most ``sqrt((f·low)² + 2·b·gap)`` for the lowest
    limit ``low`` ``gap`` m ahead (0: unknown)."""
    f = p.limit_factor
    here = np.where(limit > 0, f * limit, p.v0)
    before = np.where(low > 0, np.sqrt((f * low) ** 2 + 2.0 * p.b * np.maximum(gap, 0.0)),
                      np.inf)
    return np.minimum(here, before)


def bend_speed(route_xy: np.ndarray, a_lat: float) -> np.ndarray:
    """(A,) speed (m/s) for the sharpest bend of the route look-ahead ``route_xy`` ((A, 2·P)
    ego-frame x, y per point): ``sqrt(a_lat / κ)``, κ of the arc through each point."""
    xy = np.asarray(route_xy, np.float64).reshape(route_xy.shape[0], -1, 2)
    d2 = np.maximum((xy ** 2).sum(axis=2), 1.0)
    kappa = (2.0 * np.abs(xy[:, :, 1]) / d2).max(axis=1)
    return np.sqrt(a_lat / np.maximum(kappa, 1e-6))


def stop_brake(v: np.ndarray, gap: np.ndarray, p: IdmParams) -> np.ndarray:
    """(A,) the deceleration (m/s², ≤ 0) that stops ``s0`` before a point ``gap`` m ahead
    (a stop line, a junction conflict): ``v² / (2·(gap − s0))``, at most ``max_brake``;
    within ``hold`` m of the stopping point (or past it) ``max_brake``, which holds a standing
    car there (route-relative control does not reverse,
    :func:`magail_sumo.sim.tracking.no_reverse`) rather than letting it creep over the line, as
    a residual policy's sampling noise would around a prior of 0."""
    v = np.maximum(v, 0.0)
    room = gap - p.s0
    need = np.where(room > p.hold, v * v / (2.0 * np.maximum(room, p.hold)), p.max_brake)
    return -np.minimum(need, p.max_brake)


def light_brake(v: np.ndarray, light: np.ndarray, gap: np.ndarray, p: IdmParams,
                light_range: float) -> np.ndarray:
    """(A,) :func:`stop_brake` before a red or yellow light's stop line ``gap`` m ahead; +inf
    (no limit) for other lights or a line out of range (``gap`` ≥ ``light_range``)."""
    stop = np.isin(light, STOP_LIGHTS) & (gap < light_range - 1e-6)
    return np.where(stop, stop_brake(v, gap, p), np.inf)


def time_to_cover(d: np.ndarray, v: np.ndarray, a: float) -> np.ndarray:
    """(A,) time (s) to cover ``d`` m from speed ``v`` accelerating at ``a`` m/s²:
    ``(sqrt(v² + 2·a·d) − v) / a``."""
    v = np.maximum(v, 0.0)
    return (np.sqrt(v * v + 2.0 * a * np.maximum(d, 0.0)) - v) / a


def give_way_brake(v: np.ndarray, gap: np.ndarray, foe_time: np.ndarray, p: IdmParams,
                   give_way_range: float) -> np.ndarray:
    """(A,) :func:`stop_brake` before a junction conflict ``gap`` m ahead when the road user
    given way to (``foe_time`` s away from it) leaves too small a gap (module doc); +inf where
    the gap is accepted or there is none."""
    seen = gap < give_way_range - 1e-6
    wait = seen & (foe_time < time_to_cover(gap + p.clear, v, p.a_clear) + p.margin)
    return np.where(wait, stop_brake(v, gap, p), np.inf)


class IdmRule:
    """IDM on route-relative control as a function of observation rows (module doc).

    :param observation: the observation the rows follow; it must have the ``leader`` (or
        ``path_leader``) and ``light_gap`` features (route look-ahead points are used for
        bends when present).
    :param limits: the vehicle limits actions are normalised by.
    :param params: the IDM settings (default :class:`IdmParams`).
    :raises ValueError: an observation without the leader or the stop-line distance.
    """

    action_layout = "accel_offset"
    #: the dataclass of the rule's settings (``policy.prior_params`` overrides its fields)
    params_type = IdmParams

    def __init__(self, observation: ObservationConfig, limits: BicycleLimits | None = None,
                 params: IdmParams | None = None) -> None:
        if not ((observation.leader or observation.path_leader) and observation.light_gap):
            raise ValueError("the IDM rule reads the leader and the stop-line distance: set "
                             "observation.leader (or observation.path_leader) and "
                             "observation.light_gap to true")
        self.observation = observation
        self.limits = limits or BicycleLimits()
        self.params = params or IdmParams()
        names = observation_names(observation)
        lead = "path_leader" if observation.path_leader else "leader"
        self._col = [names.index(n) for n in ("speed", f"{lead}_gap", f"{lead}_closing",
                                              "light", "light_gap")]
        self._route = [names.index(f"route_{a}_{d:g}") for d in observation.route_points
                       for a in "xy"]
        self._give_way = [names.index(n) for n in ("give_way_gap", "give_way_time")] \
            if observation.give_way else []
        self._limit = [names.index(n) for n in ("speed_limit", "speed_limit_ahead",
                                                 "speed_limit_gap")] \
            if observation.speed_limit else []
        self._stop = names.index("route_stop_gap") if observation.route_stop else None
        self._factor = names.index("speed_factor") if observation.speed_factor else None

    def accel(self, obs: np.ndarray, v0_scale: np.ndarray | None = None) -> np.ndarray:
        """(A,) IDM acceleration (m/s²) of observation rows ``obs`` (A, D); ``v0_scale``:
        (A,) each row's desired speed as a multiple of the rule's (a driver population), on top
        of the observed ``speed_factor`` where the rows have it."""
        obs = np.asarray(obs, np.float64)
        v, gap, closing, light, to_line = (obs[:, c] for c in self._col)
        p = self.params
        none = gap >= self.observation.leader_range - 1e-6  # the sensor reads its range
        gap = np.where(none, np.inf, gap)
        closing = np.where(none, 0.0, closing)
        v0 = desired_speed(*(obs[:, c] for c in self._limit), p) if self._limit \
            else np.full(len(obs), p.v0)
        if self._factor is not None:
            v0 = v0 * obs[:, self._factor]
        if v0_scale is not None:
            v0 = v0 * np.asarray(v0_scale, np.float64)
        if self._route:
            v0 = np.minimum(v0, bend_speed(obs[:, self._route], p.a_lat))
        accel = idm_accel(v, gap, closing, p, v0)
        accel = np.minimum(accel, light_brake(v, light, to_line, p, LIGHT_RANGE))
        if self._give_way:
            conflict, foe_time = obs[:, self._give_way[0]], obs[:, self._give_way[1]]
            accel = np.minimum(accel, give_way_brake(v, conflict, foe_time, p, GIVE_WAY_RANGE))
        if self._stop is not None:
            to_end = obs[:, self._stop]
            accel = np.minimum(accel, np.where(to_end < ROUTE_STOP_RANGE - 1e-6,
                                               stop_brake(v, to_end + p.s0, p), np.inf))
        return accel

    def __call__(self, obs: np.ndarray, v0_scale: np.ndarray | None = None) -> np.ndarray:
        """(A, 2) normalised ``accel_offset`` actions of observation rows ``obs`` (A, D)
        (``v0_scale``: :meth:`accel`)."""
        accel = self.accel(obs, v0_scale)
        return normalise(accel, np.zeros_like(accel), self.limits, self.action_layout)
