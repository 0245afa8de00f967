"""Per-agent observation vectors for all agents of a step in one call.

Frames and units: scene frame = the recording's frame (m, rad CCW from +x); ego frame = origin
at the agent's box centre, +x along its heading, +y to its left. Beam ``j`` of a sensor with
``B`` beams and field of view ``fov`` points at ``-fov/2 + j·fov/B`` rad from the heading
(``fov = 2·pi``: beam 0 straight ahead, counter-clockwise from there); readings are metres to
the first hit, ``range`` when nothing is hit.

Layout ``"ego"`` (default; D = 7 + lidar + side + lane_line + 1 + 5, 113 with the defaults):

====================  ======================================================================
index (defaults)      quantity
====================  ======================================================================
0                     speed: signed speed along the heading (m/s)
1, 2                  previous action: normalised accel, steer in [-1, 1]
3, 4                  box length, width (m)
5                     lateral offset from the current lane centre (m, + = left; 0 off-lane)
6                     heading error to the current lane direction (rad, [-pi, pi))
7 .. 86               lidar: 80 beams / 30 m against other road users' oriented boxes
87 .. 96              side detector: 10 beams / 8 m against road edges
97 .. 106             lane-line detector: 10 beams / 3 m against road lines (the painted lane
                      boundaries; WOMD lane boundaries reference these lines)
107                   light of the current lane: 0 none, 1 green, 2 yellow, 3 red
108, 109              destination in the ego frame (m)
110                   distance to the destination (m)
111, 112              route direction: cos, sin of the destination heading in the ego frame
113 .. 115            (``command: true`` only) route command at the next junction, one-hot
                      left / straight / right (:mod:`magail_sumo.sensors.command`)
then 2 per distance   (``route_points`` only) route look-ahead: ego-frame x, y (m) of the
                      recorded route that many m ahead (``route_x_<d>``, ``route_y_<d>``)
then 2                (``leader: true`` only) ``leader_gap`` (m), ``leader_closing`` (m/s)
                      to the road user ahead in the agent's path
                      (:mod:`magail_sumo.sensors.units.leader`)
then 1                (``light_gap: true`` only) ``light_gap``: distance (m) to the stop line
                      of the light ahead, 50 when none
                      (:mod:`magail_sumo.sensors.units.light_gap`)
then 2                (``give_way: true`` only) ``give_way_gap`` (m), ``give_way_time`` (s):
                      the junction conflict of the road user to give way to, 50 / 10 when
                      none (:mod:`magail_sumo.sensors.units.give_way`)
then 2                (``path_leader: true`` only) ``path_leader_gap`` (m),
                      ``path_leader_closing`` (m/s) to the road user in the agent's lane
                      corridor ahead along its reference path
                      (:mod:`magail_sumo.sensors.units.path_leader`)
then 3                (``speed_limit: true`` only) ``speed_limit``, ``speed_limit_ahead``
                      (m/s), ``speed_limit_gap`` (m): the speed limit on the agent's path
                      here and the lowest one ahead with its distance, 0 when unknown
                      (:mod:`magail_sumo.sensors.units.speed_limit`)
then 1                (``route_stop: true`` only) ``route_stop_gap`` (m): along the recorded
                      route to its end where the recorded driver stands still, 50 when none
                      (:mod:`magail_sumo.sensors.units.route_stop`)
then 1                (``speed_factor: true`` only) ``speed_factor``: the agent's desired
                      speed as a multiple of the road's, 1 in recorded scenes
                      (:mod:`magail_sumo.sensors.units.speed_factor`)
====================  ======================================================================

Layout ``"scene_frame"`` (108 values with the defaults, the MAGAIL4AutoDrive observation; its
deprecated name ``"seed"`` is still read): position x, y (scene frame, m) 0–1; velocity vx, vy
(scene frame, m/s) 2–3; heading (scene frame, rad) 4; lidar 5–84; side detector 85–94;
lane-line detector 95–104; light 105; destination x, y (scene frame, m) 106–107 (with
``command: true`` the 3 command values follow).

The current lane is the nearest lane centre line running within 90° of the heading
(:class:`~magail_sumo.sensors.lanes.LaneIndex`); its light comes from the suite's light source
(:class:`~magail_sumo.sensors.traffic_lights.LightTable` of a recording, or a live code the env
passes). :meth:`SensorSuite.observe` runs the numba kernels of
:mod:`magail_sumo.sensors.raycast` over all agents at once.

Each block above is a sensor unit (:mod:`magail_sumo.sensors.base`, one module each under
:mod:`magail_sumo.sensors.units`): it declares its names, bounds and reading, and a layout
(:data:`~magail_sumo.sensors.base.LAYOUTS`) lists the units in order — ``ego``: ``ego``,
``lane``, ``lidar``, ``side``, ``lane_line``, ``light``, ``destination``; ``scene_frame``:
``scene_pose``, ``lidar``, ``side``, ``lane_line``, ``light``, ``scene_destination``; then
``command`` with ``command: true``, ``route`` with ``route_points``, ``leader`` with
``leader: true``, ``light_gap`` with ``light_gap: true``, ``give_way`` with ``give_way: true``,
``path_leader`` with ``path_leader: true``, ``speed_limit`` with ``speed_limit: true``,
``route_stop`` with ``route_stop: true`` and ``speed_factor`` with ``speed_factor: true``. The
suite is built from a road map and a light source (:meth:`SensorSuite.from_map`;
``SensorSuite(scene, config)`` for a recorded scene).
"""

from __future__ import annotations

from collections import Counter
from typing import Sequence

import numpy as np

from magail_sumo.scene import RoadMap, Scene

from .base import (
    Boxes, EgoState, PathAhead, Sensor, SensorInput, SensorMaps, sensor_class, sensor_order,
)
from .command import COMMAND_NAMES
from .config import TWO_PI, BeamSpec, ObservationConfig
from .lanes import LaneQuery
from .traffic_lights import NO_LIGHTS, LightSource, LightTable

__all__ = ["COMMAND_NAMES", "TWO_PI", "BeamSpec", "Boxes", "EgoState", "ObservationConfig",
           "PathAhead", "SensorSuite", "observation_bounds", "observation_names"]


def _sensor_classes(cfg: ObservationConfig, sensors: Sequence[str] | None) -> list[type[Sensor]]:
    return [sensor_class(n) for n in (sensor_order(cfg) if sensors is None else sensors)]


def observation_names(config: ObservationConfig | None = None,
                      sensors: Sequence[str] | None = None) -> list[str]:
    """Name of every entry of the observation vector, in order.

    :param sensors: registered sensor names to concatenate instead of the config's layout.
    """
    cfg = config or ObservationConfig()
    names = [n for cls in _sensor_classes(cfg, sensors) for n in cls.names(cfg)]
    dup = sorted(n for n, c in Counter(names).items() if c > 1)
    if dup:
        raise ValueError(f"observation features named twice: {', '.join(dup)} (sensors "
                         f"{', '.join(sensor_order(cfg) if sensors is None else sensors)})")
    return names


def observation_bounds(config: ObservationConfig | None = None,
                       sensors: Sequence[str] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) float32 bounds of every entry (inf where unbounded)."""
    cfg = config or ObservationConfig()
    parts = [cls.bounds(cfg) for cls in _sensor_classes(cfg, sensors)]
    if not parts:
        return np.zeros(0, np.float32), np.zeros(0, np.float32)
    return (np.concatenate([p[0] for p in parts]).astype(np.float32),
            np.concatenate([p[1] for p in parts]).astype(np.float32))


class SensorSuite:
    """Static sensor geometry of one map (built once) and the observation of every agent: the
    sensors of the config's layout (or ``sensors``), concatenated in order (module doc).

    ``SensorSuite(scene, config)`` is the suite of a recorded scene (its road map and recorded
    lights); :meth:`from_map` builds one from a road map and a light source.
    """

    def __init__(self, scene: Scene, config: ObservationConfig | None = None,
                 sensors: Sequence[str] | None = None) -> None:
        self._build(scene.roadmap, LightTable.build(scene), config, sensors)

    @classmethod
    def from_map(cls, roadmap: RoadMap, lights: LightSource | None = None,
                 config: ObservationConfig | None = None,
                 sensors: Sequence[str] | None = None) -> "SensorSuite":
        """The suite over ``roadmap`` reading lights from ``lights`` (None: no recorded
        signals, :data:`~magail_sumo.sensors.traffic_lights.NO_LIGHTS`).

        :param sensors: registered sensor names to concatenate instead of the config's layout.
        """
        suite = cls.__new__(cls)
        suite._build(roadmap, NO_LIGHTS if lights is None else lights, config, sensors)
        return suite

    def _build(self, roadmap: RoadMap, lights: LightSource, config: ObservationConfig | None,
               sensors: Sequence[str] | None) -> None:
        self.config = cfg = config or ObservationConfig()
        self.maps = SensorMaps(roadmap, lights, cfg.lane_cell)
        self.lanes = self.maps.lanes
        self.lights = lights
        self.names = observation_names(cfg, sensors)
        self.size = len(self.names)
        #: the sensor units, in observation order
        self.sensors: tuple[Sensor, ...] = tuple(cls(cfg, self.maps)
                                                 for cls in _sensor_classes(cfg, sensors))
        self._widths = [len(s.names(cfg)) for s in self.sensors]

    def lane_query(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> LaneQuery:
        """Current lane (see :class:`LaneQuery`) of A poses."""
        return self.lanes.query(x, y, yaw)

    def observe(self, boxes: Boxes, ego: EgoState, step: int,
                lanes: LaneQuery | None = None, light: np.ndarray | None = None,
                light_gap: np.ndarray | None = None,
                give_way: np.ndarray | None = None) -> np.ndarray:
        """(A, D) float32 observations of the agents at log step ``step`` (layout: module doc).

        :param lanes: the agents' :meth:`lane_query` when already computed this step.
        :param light: (A,) current-lane light codes (0 none, 1 green, 2 yellow, 3 red) from a
            live source (a SUMO run without a recording); default: the suite's light source.
        :param light_gap: (A,) live distances (m) to that light's stop line (inf: none);
            default: from the suite's maps.
        :param give_way: (A, 2) live give-way conflict: distance (m), the road user's time to
            it (s) (inf: none); default: none.
        """
        a = np.asarray(ego.index).shape[0]
        if a == 0:
            return np.zeros((0, self.size), np.float32)
        inp = SensorInput(self.maps, boxes, ego, step, lanes, light, light_gap, give_way)
        out = np.empty((a, self.size), np.float32)
        k = 0
        for sensor, width in zip(self.sensors, self._widths):  # a fixed handful, not per agent
            block = np.asarray(sensor.read(inp)).reshape(a, -1)
            if block.shape[1] != width:
                raise ValueError(f"sensor {sensor.name!r} read {block.shape[1]} values per agent "
                                 f"but declares {width} names")
            out[:, k:k + width] = block
            k += width
        return out
