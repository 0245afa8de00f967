"""Desired-speed factor: how fast the agent itself wants to drive, as a multiple of the road's
speed (appended with ``ObservationConfig.speed_factor``).

``speed_factor`` (dimensionless) is, in a city, the factor SUMO drew for the vehicle when it
entered the network from its type's ``speedFactor`` distribution (SUMO's default for cars:
mean 1, deviation 0.1, cut at 0.2 and 2; a scenario may give its own), read once when the
vehicle becomes an agent: the same population of desires SUMO's own drivers have. A SUMO driver
drives at most the lane's speed limit times its factor; the IDM prior
(:class:`magail_sumo.models.idm.IdmRule`) scales its desired speed by it the same way. In a
recorded scene it reads 1: what the recorded driver wanted is not observed, and drawing it
would add noise to the recorded-scene policy that the log does not have.
"""

from __future__ import annotations

import numpy as np

from ..base import Sensor, SensorInput, bounded, register

#: the highest factor reported (SUMO cuts its default distribution at 2)
MAX_FACTOR = 2.0


@register
class SpeedFactor(Sensor):
    """``speed_factor``: the agent's desired speed over the road's (module doc)."""

    name = "speed_factor"

    @classmethod
    def names(cls, config) -> list[str]:
        return ["speed_factor"]

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        return bounded(1, 0, MAX_FACTOR)

    def read(self, inp: SensorInput) -> np.ndarray:
        factor = inp.ego.speed_factor
        if factor is None:
            return np.ones((len(inp), 1), np.float32)
        return np.clip(np.asarray(factor, np.float64), 0.0, MAX_FACTOR
                       ).astype(np.float32)[:, None]
