"""Route look-ahead: where the agent's recorded route runs ahead of it, in the ego frame
(:meth:`magail_sumo.sensors.command.RouteCommands.ahead`); appended with
``ObservationConfig.route_points``."""

from __future__ import annotations

import numpy as np

from ..base import Sensor, SensorInput, register


def _label(d: float) -> str:
    return f"{d:g}".replace(".", "p")


@register
class RouteAhead(Sensor):
    """``route_x_<d>``, ``route_y_<d>`` for each distance ``d`` of ``route_points``: the
    recorded route's position ``d`` m (along the route) ahead of the agent's progress point, in
    the ego frame (m; +x along the heading, +y to the left). Zeros for every agent when the env
    has no recorded routes (a city)."""

    name = "route"

    @classmethod
    def names(cls, config) -> list[str]:
        return [f"route_{axis}_{_label(d)}" for d in config.route_points for axis in "xy"]

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        n = 2 * len(config.route_points)
        return np.full(n, -np.inf, np.float32), np.full(n, np.inf, np.float32)

    def read(self, inp: SensorInput) -> np.ndarray:
        if inp.ego.route is None:
            return np.zeros((len(inp), 2 * len(self.config.route_points)), np.float32)
        return inp.ego.route
