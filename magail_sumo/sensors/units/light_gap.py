"""Stop-line distance: how far ahead the stop line of the light the agent sees is (appended with
``ObservationConfig.light_gap``).

``light_gap`` (m) is the distance to the stop line of the ``light`` observation's signal, capped
at :data:`LIGHT_RANGE` (the value when no light is ahead: none, or the agent is past its stop
line). In a recorded scene the stop line of an approach lane is where it ends (WOMD records a
signal on the lanes that start at the stop line, and an approach lane shows its exits' signal,
:mod:`magail_sumo.sensors.traffic_lights`), measured straight from the agent's box centre; in a
SUMO run the env passes SUMO's own distance along the route to the next signal
(``traci.vehicle.getNextTLS``). With it a driver can stop at the line rather than guess where it
is.
"""

from __future__ import annotations

import numpy as np

from ..base import Sensor, SensorInput, bounded, register

#: the farthest stop line reported (m); also what reads when none is ahead
LIGHT_RANGE = 50.0


@register
class LightGap(Sensor):
    """``light_gap``: metres to the stop line of the light ahead (module doc)."""

    name = "light_gap"

    @classmethod
    def names(cls, config) -> list[str]:
        return ["light_gap"]

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        return bounded(1, 0, LIGHT_RANGE)

    def read(self, inp: SensorInput) -> np.ndarray:
        gap = np.where(inp.light > 0, inp.light_gap, np.inf)
        return np.clip(gap, 0.0, LIGHT_RANGE)[:, None]
