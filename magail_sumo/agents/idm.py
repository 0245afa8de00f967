"""A rule-based route follower: the Intelligent Driver Model on route-relative control.

:class:`IdmPolicy` drives each agent along its route (``action_layout: accel_offset``: zero
lateral offset, pure pursuit keeps it on the route's lanes, :mod:`magail_sumo.sim.tracking`)
with the IDM acceleration (Treiber, Hennecke & Helbing 2000) towards the road user ahead in its
path (the ``leader`` observation: gap ``s`` m, closing speed ``Δv`` m/s):

    a = a_max · [1 − (v / v0)^4 − (s* / s)^2],   s* = s0 + v·T + v·Δv / (2·sqrt(a_max·b))

(free road: no interaction term), with the desired speed lowered before bends: the route
look-ahead (``route_points`` 5, 10, 20 m) gives each point's curvature ``κ = 2·|y| / (x² + y²)``
(the arc from the car through it), and ``v0`` is at most ``sqrt(a_lat / κ)`` (lateral
acceleration ``a_lat``). The ``light`` observation says a red or yellow light is
ahead (within the sensor's 50 m) but not where its stop line is: an agent that starts seeing one
assumes the line ``light_gap`` m ahead, counts the distance down as it drives (its own speed ×
0.1 s per step) and brakes to stop ``s0`` before it (``v² / (2·d)``, at most ``max_brake``);
it keeps the IDM acceleration when that is lower. It reads nothing but its observations (and
remembers that countdown per agent), so it is a baseline for what route-relative control makes
possible without learning, not a model of the recorded drivers: the built-in policy
``--policy idm``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magail_sumo.sensors.observation import ObservationConfig, observation_names
from magail_sumo.sim.dynamics import BicycleLimits, normalise

#: light codes of the ``light`` observation that stop an IDM driver (yellow, red)
STOP_LIGHTS = (2.0, 3.0)


@dataclass(frozen=True)
class IdmParams:
    """IDM parameters (urban defaults).

    :param v0: desired speed (m/s). :param T: time headway (s). :param s0: standstill gap (m).
    :param a_max: maximum acceleration (m/s²). :param b: comfortable deceleration (m/s²).
    :param light_gap: distance (m) to the stop line of a red or yellow light when it is
        first seen.
    :param max_brake: the hardest braking for a light (m/s²).
    :param a_lat: the lateral acceleration bends are taken at (m/s²).
    :param dt: the env's step (s).
    """

    v0: float = 13.9
    T: float = 1.5
    s0: float = 2.0
    a_max: float = 1.5
    b: float = 2.0
    light_gap: float = 45.0
    max_brake: float = 6.0
    a_lat: float = 2.0
    dt: float = 0.1


#: route look-ahead distances the policy observes (m)
ROUTE_POINTS = (5.0, 10.0, 20.0)


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


def bend_speed(route_xy: np.ndarray, a_lat: float) -> np.ndarray:
    """(A,) speed (m/s) for the sharpest bend of the route look-ahead ``route_xy`` ((A, 2·P)
    ego-frame x, y per point): ``sqrt(a_lat / κ)``, κ of the arc through each point."""
    xy = np.asarray(route_xy, np.float64).reshape(route_xy.shape[0], -1, 2)
    d2 = np.maximum((xy ** 2).sum(axis=2), 1.0)
    kappa = (2.0 * np.abs(xy[:, :, 1]) / d2).max(axis=1)
    return np.sqrt(a_lat / np.maximum(kappa, 1e-6))


class IdmPolicy:
    """IDM along the route (module doc); ``seed`` is unused (the policy is deterministic)."""

    action_layout = "accel_offset"

    def __init__(self, seed: int = 0, params: IdmParams | None = None) -> None:
        self.params = params or IdmParams()
        self.observation = ObservationConfig(leader=True, route_points=ROUTE_POINTS)
        self.limits = BicycleLimits()
        names = observation_names(self.observation)
        self._col = {n: names.index(n) for n in ("speed", "leader_gap", "leader_closing",
                                                 "light")}
        self._route = [names.index(f"route_{a}_{d:g}") for d in ROUTE_POINTS for a in "xy"]
        self._range = self.observation.leader_range
        #: per agent seeing a red / yellow light: metres left to its assumed stop line
        self._to_line: dict[str, float] = {}

    def reseed(self, seed: int) -> None:
        """A fresh rollout: no light remembered."""
        self._to_line = {}

    def act(self, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if not observations:
            return {}
        names = list(observations)
        obs = np.stack([observations[n] for n in names]).astype(np.float64)
        c, p = self._col, self.params
        v = obs[:, c["speed"]]
        gap = obs[:, c["leader_gap"]]
        closing = obs[:, c["leader_closing"]]
        none = gap >= self._range - 1e-6  # the leader sensor reports its range for "none"
        gap = np.where(none, np.inf, gap)
        closing = np.where(none, 0.0, closing)
        accel = idm_accel(v, gap, closing, p,
                          np.minimum(p.v0, bend_speed(obs[:, self._route], p.a_lat)))
        stop = np.isin(obs[:, c["light"]], STOP_LIGHTS)
        left = np.full(len(names), np.inf)
        seen = self._to_line
        for i, (n, red) in enumerate(zip(names, stop.tolist())):  # per-agent memory (dict)
            if red:
                left[i] = seen[n] = seen.get(n, p.light_gap) - max(v[i], 0.0) * p.dt
            else:
                seen.pop(n, None)
        room = np.maximum(left - p.s0, 0.5)
        brake = -np.minimum(v * v / (2.0 * room), p.max_brake)
        accel = np.where(stop, np.minimum(accel, brake), accel)
        act = normalise(accel, np.zeros_like(accel), self.limits, self.action_layout)
        return dict(zip(names, act.astype(np.float32)))
