"""Route stop: how far ahead the recorded route ends with its driver standing still (appended
with ``ObservationConfig.route_stop``).

``route_stop_gap`` (m) is the distance along the agent's recorded route from its progress point
(:meth:`magail_sumo.sensors.command.RouteCommands.stop_ahead`) to the route's last valid state,
where the recorded driver's speed there is below :data:`~magail_sumo.sensors.command.STANDING`
(a car that parks, or comes to a halt in a queue or at a line and is still standing when its
record ends), capped at :data:`ROUTE_STOP_RANGE`. It reads the cap where the route ends with
the driver moving (the record ends, the driver drives on), beyond the cap, past the route's
end (0 there) excepted, and where there are no recorded routes (a city: SUMO's drivers arrive
at speed). Like the route look-ahead it is navigation intent from the log: where the route
goes, and whether it ends there.
"""

from __future__ import annotations

import numpy as np

from ..base import Sensor, SensorInput, bounded, register

#: the farthest standing end reported (m); also what reads when there is none
ROUTE_STOP_RANGE = 50.0


@register
class RouteStop(Sensor):
    """``route_stop_gap``: metres along the recorded route to its standing end (module doc)."""

    name = "route_stop"

    @classmethod
    def names(cls, config) -> list[str]:
        return ["route_stop_gap"]

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        return bounded(1, 0, ROUTE_STOP_RANGE)

    def read(self, inp: SensorInput) -> np.ndarray:
        gap = inp.ego.route_stop
        if gap is None:
            return np.full((len(inp), 1), ROUTE_STOP_RANGE, np.float32)
        return np.clip(np.asarray(gap, np.float64), 0.0, ROUTE_STOP_RANGE
                       ).astype(np.float32)[:, None]
