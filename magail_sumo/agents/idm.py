"""A rule-based route follower: the Intelligent Driver Model on route-relative control.

:class:`IdmPolicy` drives each agent along its route (``action_layout: accel_offset``: zero
lateral offset, pure pursuit keeps it on the route's lanes, :mod:`magail_sumo.sim.tracking`)
with the IDM acceleration towards the road user ahead in its lane corridor along the route (the
path leader, :mod:`magail_sumo.sensors.units.path_leader`), slowing before bends seen in
the route look-ahead (5, 10, 20 m), stopping at the stop line of a red or yellow light and
giving way at junctions (in SUMO runs, where the junction model says so): the rule of
:class:`magail_sumo.models.idm.IdmRule`, which has the equations. It reads nothing but its
observations and keeps no memory, so it is a baseline for what route-relative control makes
possible without learning, not a model of the recorded drivers: the built-in policy
``--policy idm``. It does not drive behind the gap guard (:mod:`magail_sumo.env.guard`): on
the Wildau city the guard took collisions and off-road exits from 10.7 % to 1.3 % of the
agents but halved the trips (308 → 187 of SUMO's 388): it stops agents for vehicles
converging on their path with no notion of who has the way (``docs/results/city.md``).
"""

from __future__ import annotations

import zlib

import numpy as np

from magail_sumo.models.idm import IdmParams, IdmRule
from magail_sumo.sensors.observation import ObservationConfig
from magail_sumo.sim.dynamics import BicycleLimits

#: route look-ahead distances the policy observes (m)
ROUTE_POINTS = (5.0, 10.0, 20.0)
#: deviation of the agents' desired-speed factors (SUMO's default ``speedDev``)
SPEED_DEV = 0.1


class IdmPolicy:
    """IDM along the route (module doc). Its agents are a population of drivers: each one's
    desired speed is the rule's times its own factor, drawn once per agent (by name and
    ``seed``) from a normal distribution of mean 1 and deviation ``speed_dev`` cut at two
    deviations, as SUMO draws its drivers' ``speedFactor`` (deviation 0.1 by default); 0: every
    agent the same. With ``speed_limits`` it also reads the road's speed limits and drives at
    them (:mod:`magail_sumo.sensors.units.speed_limit`): off by default, as on cologne8 it then
    completed 57 fewer of 383 trips in 10 min (``docs/results/city.md``)."""

    action_layout = IdmRule.action_layout

    def __init__(self, seed: int = 0, params: IdmParams | None = None,
                 speed_limits: bool = False, speed_dev: float = SPEED_DEV) -> None:
        self.observation = ObservationConfig(leader=True, light_gap=True, give_way=True,
                                             path_leader=True, route_points=ROUTE_POINTS,
                                             speed_limit=speed_limits)
        self.limits = BicycleLimits()
        self.rule = IdmRule(self.observation, self.limits, params)
        self.speed_dev = float(speed_dev)
        self._seed = int(seed)
        self._factor: dict[str, float] = {}

    def speed_factor(self, name: str) -> float:
        """Agent ``name``'s desired-speed factor (class doc)."""
        f = self._factor.get(name)
        if f is None:
            z = np.random.default_rng([self._seed, zlib.crc32(name.encode())]).standard_normal()
            f = self._factor[name] = 1.0 + self.speed_dev * float(np.clip(z, -2.0, 2.0))
        return f

    @property
    def params(self) -> IdmParams:
        """The rule's IDM parameters."""
        return self.rule.params

    def reseed(self, seed: int) -> None:
        """A fresh rollout: a fresh population of desired speeds (the rule keeps no memory)."""
        self._seed = int(seed)
        self._factor.clear()

    def act(self, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if not observations:
            return {}
        names = list(observations)
        scale = np.array([self.speed_factor(n) for n in names]) if self.speed_dev else None
        act = self.rule(np.stack([observations[n] for n in names]), scale)
        return dict(zip(names, act.astype(np.float32)))
