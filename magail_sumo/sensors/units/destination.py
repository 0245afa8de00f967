"""Destination in the ego frame (layout ``ego``): origin at the agent's box centre, +x along
its heading, +y to its left."""

from __future__ import annotations

import numpy as np

from ..base import Sensor, SensorInput, register


@register
class Destination(Sensor):
    """``dest_x``, ``dest_y``: destination in the ego frame (m); ``dest_distance`` (m);
    ``route_cos``, ``route_sin``: the destination heading in the ego frame."""

    name = "destination"

    @classmethod
    def names(cls, config) -> list[str]:
        return ["dest_x", "dest_y", "dest_distance", "route_cos", "route_sin"]

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        low = np.array([-np.inf, -np.inf, 0.0, -1.0, -1.0], np.float32)
        high = np.array([np.inf, np.inf, np.inf, 1.0, 1.0], np.float32)
        return low, high

    def read(self, inp: SensorInput) -> np.ndarray:
        ego, yaw = inp.ego, inp.yaw
        dx, dy = ego.destination[:, 0] - inp.x, ego.destination[:, 1] - inp.y
        c, s = np.cos(yaw), np.sin(yaw)
        rel = ego.destination_yaw - yaw
        return np.stack([c * dx + s * dy, -s * dx + c * dy, np.hypot(dx, dy), np.cos(rel),
                         np.sin(rel)], axis=1)
