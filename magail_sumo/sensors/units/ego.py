"""Ego motion: the agent's own speed, previous action and box size (layout ``ego``)."""

from __future__ import annotations

import numpy as np

from ..base import Sensor, SensorInput, register


@register
class EgoMotion(Sensor):
    """``speed`` (signed, along the heading, m/s), ``prev_accel``, ``prev_steer`` (the previous
    normalised action, [-1, 1]) and the box ``length``, ``width`` (m)."""

    name = "ego"

    @classmethod
    def names(cls, config) -> list[str]:
        return ["speed", "prev_accel", "prev_steer", "length", "width"]

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        low = np.array([-np.inf, -1.0, -1.0, 0.0, 0.0], np.float32)
        high = np.array([np.inf, 1.0, 1.0, np.inf, np.inf], np.float32)
        return low, high

    def read(self, inp: SensorInput) -> np.ndarray:
        ego, boxes, idx = inp.ego, inp.boxes, inp.index
        return np.stack([ego.speed, ego.prev_action[:, 0], ego.prev_action[:, 1],
                         boxes.length[idx], boxes.width[idx]], axis=1)
