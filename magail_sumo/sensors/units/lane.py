"""Pose relative to the current lane (layout ``ego``): the nearest lane centre line running
within 90° of the heading (:class:`~magail_sumo.sensors.lanes.LaneIndex`)."""

from __future__ import annotations

import numpy as np

from ..base import Sensor, SensorInput, register


@register
class LanePose(Sensor):
    """``lane_lateral``: offset from the current lane's centre line (m, + = left; 0 off-lane);
    ``lane_heading_error``: heading minus lane direction (rad, [-pi, pi))."""

    name = "lane"

    @classmethod
    def names(cls, config) -> list[str]:
        return ["lane_lateral", "lane_heading_error"]

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        return (np.array([-np.inf, -np.pi], np.float32), np.array([np.inf, np.pi], np.float32))

    def read(self, inp: SensorInput) -> np.ndarray:
        lq = inp.lanes
        return np.stack([lq.lateral, lq.heading_error], axis=1)
