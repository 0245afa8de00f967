"""Traffic light of the current lane: 0 none, 1 green, 2 yellow, 3 red, from the maps' light
source (:mod:`magail_sumo.sensors.traffic_lights`) or a live source the env passes."""

from __future__ import annotations

import numpy as np

from ..base import Sensor, SensorInput, bounded, register


@register
class CurrentLight(Sensor):
    """``light``: the light code of the agent's current lane."""

    name = "light"

    @classmethod
    def names(cls, config) -> list[str]:
        return ["light"]

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        return bounded(1, 0, 3)

    def read(self, inp: SensorInput) -> np.ndarray:
        return inp.light[:, None]
