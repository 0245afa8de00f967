"""Route command at the next junction, one-hot left / straight / right
(:mod:`magail_sumo.sensors.command`); appended with ``ObservationConfig.command``."""

from __future__ import annotations

import numpy as np

from ..base import Sensor, SensorInput, bounded, register
from ..command import COMMAND_NAMES, STRAIGHT, one_hot


@register
class RouteCommand(Sensor):
    """``command_left``, ``command_straight``, ``command_right``: the agents'
    ``EgoState.command``, ``straight`` for every agent when the env has none (a city)."""

    name = "command"

    @classmethod
    def names(cls, config) -> list[str]:
        return list(COMMAND_NAMES)

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        return bounded(len(COMMAND_NAMES), 0.0, 1.0)

    def read(self, inp: SensorInput) -> np.ndarray:
        if inp.ego.command is None:
            return one_hot(np.full(len(inp), STRAIGHT))
        return inp.ego.command
