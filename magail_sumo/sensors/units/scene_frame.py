"""Scene-frame quantities of the ``scene_frame`` layout (the MAGAIL4AutoDrive observation): the
agent's pose and velocity, and its destination, in the scene frame (absolute map coordinates)."""

from __future__ import annotations

import numpy as np

from ..base import Sensor, SensorInput, register


@register
class ScenePose(Sensor):
    """``x``, ``y`` (m), ``vx``, ``vy`` (m/s) and ``heading`` (rad, [-pi, pi]), scene frame."""

    name = "scene_pose"
    scene_frame = True

    @classmethod
    def names(cls, config) -> list[str]:
        return ["x", "y", "vx", "vy", "heading"]

    @classmethod
    def bounds(cls, config) -> tuple[np.ndarray, np.ndarray]:
        inf = np.inf
        return (np.array([-inf, -inf, -inf, -inf, -np.pi], np.float32),
                np.array([inf, inf, inf, inf, np.pi], np.float32))

    def read(self, inp: SensorInput) -> np.ndarray:
        speed, yaw = inp.ego.speed, inp.yaw
        return np.stack([inp.x, inp.y, speed * np.cos(yaw), speed * np.sin(yaw), yaw], axis=1)


@register
class SceneDestination(Sensor):
    """``dest_x``, ``dest_y``: the destination in the scene frame (m)."""

    name = "scene_destination"
    scene_frame = True

    @classmethod
    def names(cls, config) -> list[str]:
        return ["dest_x", "dest_y"]

    def read(self, inp: SensorInput) -> np.ndarray:
        return inp.ego.destination[:, :2]
