"""Sensor units: the interface every sensor implements, what it reads, and the registries.

A sensor (:class:`Sensor` subclass, one module each under :mod:`magail_sumo.sensors.units`)
declares

* its feature names and (low, high) bounds for an :class:`ObservationConfig` (class methods:
  the observation layout is known without a map, e.g. to size a policy);
* what it builds once per map, in ``__init__(config, maps)`` over the :class:`SensorMaps`
  (a road map, a light source and the lane index shared by the sensors that need it);
* its reading of one step, :meth:`Sensor.read` over a :class:`SensorInput` (the road users'
  boxes, the observing agents' :class:`EgoState`, the log step, and the current lane and light
  of each agent, computed once per step when a sensor first asks).

:func:`register` files a sensor class by its ``name``; a *layout* is an ordered list of sensor
names (:data:`LAYOUTS`, :func:`register_layout`); :class:`~magail_sumo.sensors.observation.
SensorSuite` concatenates the layout's sensors in that order. Adding a sensor is one new module
plus one :func:`register` (and its name in a layout, or in a suite's ``sensors``).

Frames and units: scene frame = the recording's frame (m, rad CCW from +x).
"""

from __future__ import annotations

import warnings
from abc import ABC, abstractmethod
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, ClassVar, Sequence

import numpy as np

from magail_sumo.scene import RoadMap

from .lanes import LaneIndex, LaneQuery
from .raycast import box_edges
from .worlds import BoxGroups

if TYPE_CHECKING:
    from magail_sumo.sim.paths import Paths

    from .config import ObservationConfig
    from .traffic_lights import LightSource


@dataclass(frozen=True)
class Boxes:
    """Oriented boxes of every road user in the sensor world at one step (N,) arrays.

    :param x, y: box centre (m, scene frame). :param yaw: heading (rad, scene frame).
    :param length, width: box size (m).
    :param speed: signed speed along the heading (m/s), for sensors that read motion (the
        leader sensor); None: unknown (such sensors then read every road user as still).
    :param groups: the worlds of a batched env's boxes (:mod:`magail_sumo.sensors.worlds`):
        an agent only meets its own world's road users and the shared ones; None: one world.
    """

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    length: np.ndarray
    width: np.ndarray
    speed: np.ndarray | None = None
    groups: BoxGroups | None = None

    def __len__(self) -> int:
        return int(self.x.shape[0])

    def edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(4N, 2) edge starts, ends and (4N,) owning box index."""
        n = len(self)
        centre = np.stack([self.x, self.y], axis=1)
        half = 0.5 * np.stack([self.length, self.width], axis=1)
        e = box_edges(centre, half, np.asarray(self.yaw, np.float64))
        return (e[:, :, 0].reshape(-1, 2), e[:, :, 1].reshape(-1, 2),
                np.repeat(np.arange(n, dtype=np.int64), 4))


@dataclass(frozen=True)
class EgoState:
    """The observing agents (A,): rows of :class:`Boxes` plus what boxes do not carry.

    :param index: (A,) row of each agent in the boxes (its own box is not seen).
    :param speed: (A,) signed speed along the heading (m/s).
    :param prev_action: (A, 2) previous normalised action (accel, steer).
    :param destination: (A, 2) destination (m, scene frame).
    :param destination_yaw: (A,) heading at the destination (rad, scene frame).
    :param command: (A, 3) route-command one-hot (:mod:`magail_sumo.sensors.command`), used
        with ``ObservationConfig.command``; None: ``straight`` for every agent (an env without
        recorded routes, e.g. a city).
    :param route: (A, 2·P) route look-ahead, x and y (m, ego frame) of each of the P
        ``ObservationConfig.route_points``, used with them; None: zeros (no recorded routes).
    :param path: the agents' reference paths (:class:`PathAhead`), read by the path leader
        (``ObservationConfig.path_leader``) and the speed limits
        (``ObservationConfig.speed_limit``); None: none (free steering).
    :param route_stop: (A,) distance (m) along the recorded route to its end where the
        recorded driver stands there (``ObservationConfig.route_stop``); inf where it does not;
        None: none for every agent (no recorded routes, e.g. a city).
    :param speed_factor: (A,) each agent's desired speed as a multiple of the road's
        (``ObservationConfig.speed_factor``); None: 1 for every agent.
    """

    index: np.ndarray
    speed: np.ndarray
    prev_action: np.ndarray
    destination: np.ndarray
    destination_yaw: np.ndarray
    command: np.ndarray | None = None
    route: np.ndarray | None = None
    path: "PathAhead | None" = None
    route_stop: np.ndarray | None = None
    speed_factor: np.ndarray | None = None


@dataclass(frozen=True)
class PathAhead:
    """The observing agents' (A,) reference paths: rows ``rows`` of the path store ``paths``
    (:class:`~magail_sumo.sim.paths.Paths`; -1: no path), their progress point indices
    ``at`` (within each path) and arc lengths ``s`` (m) of their positions on them."""

    paths: "Paths"
    rows: np.ndarray
    at: np.ndarray
    s: np.ndarray


class SensorMaps:
    """The static world of the sensors of one map, built once: the road map, the light source
    and the lane index (``lane_cell`` m cells) that lane and light sensors share."""

    def __init__(self, roadmap: RoadMap, lights: "LightSource", lane_cell: float) -> None:
        self.roadmap = roadmap
        self.lights = lights
        self.lanes = LaneIndex.build(roadmap.lanes, cell=lane_cell)

    @cached_property
    def lane_ends(self) -> np.ndarray:
        """(L, 2) the last point (x, y) of each lane's centre line (m, scene frame)."""
        ends = [l.polyline[-1, :2] for l in self.roadmap.lanes]
        return np.asarray(ends, np.float64).reshape(-1, 2)


class SensorInput:
    """What the sensors read at one step, for the A observing agents (rows ``ego.index`` of
    ``boxes``): their pose (``x``, ``y``, ``yaw`` (float64), ``origins`` (A, 2)), and on first
    use their current lane (:attr:`lanes`) and its light (:attr:`light`).

    :param lanes: the agents' lane query when the caller already computed it this step.
    :param light: (A,) live light codes (0 none, 1 green, 2 yellow, 3 red); default: the
        maps' light source at log step ``step`` on each agent's current lane.
    :param light_gap: (A,) live distances (m) to the stop line of that light (inf: none
        ahead); default: from the maps (:attr:`light_gap`).
    :param give_way: (A, 2) live distance (m) to the conflict point of the road user to give
        way to and its time (s) to reach it (inf, inf: none); default: none (no junction
        model without SUMO).
    """

    def __init__(self, maps: SensorMaps, boxes: Boxes, ego: EgoState, step: int,
                 lanes: LaneQuery | None = None, light: np.ndarray | None = None,
                 light_gap: np.ndarray | None = None,
                 give_way: np.ndarray | None = None) -> None:
        self.maps, self.boxes, self.ego, self.step = maps, boxes, ego, step
        self.index = idx = np.asarray(ego.index, np.int64)
        self.x, self.y = boxes.x[idx], boxes.y[idx]
        self.yaw = np.asarray(boxes.yaw, np.float64)[idx]
        self.origins = np.stack([self.x, self.y], axis=1)
        self._lanes, self._light, self._light_gap = lanes, light, light_gap
        self._give_way = give_way

    def __len__(self) -> int:
        return int(self.index.shape[0])

    @cached_property
    def lanes(self) -> LaneQuery:
        """The agents' current lanes (:class:`~magail_sumo.sensors.lanes.LaneQuery`)."""
        if self._lanes is not None:
            return self._lanes
        return self.maps.lanes.query(self.x, self.y, self.yaw)

    @cached_property
    def light(self) -> np.ndarray:
        """(A,) float64 light code of each agent's current lane (live when given)."""
        light = self.maps.lights.lookup(self.step, self.lanes.lane) if self._light is None \
            else np.asarray(self._light)
        return light.astype(np.float64)

    @cached_property
    def give_way(self) -> np.ndarray:
        """(A, 2) float64 give-way conflict (distance m, the road user's time s to it) when
        given live; inf, inf (none) otherwise: only SUMO has a junction model."""
        if self._give_way is None:
            return np.full((len(self), 2), np.inf)
        return np.asarray(self._give_way, np.float64).reshape(len(self), 2)

    @cached_property
    def light_gap(self) -> np.ndarray:
        """(A,) float64 distance (m) to the stop line of the current lane's light, inf when
        none is ahead: live when given; from a recording, the straight distance to the end of
        an approach lane that shows its exits' signal (WOMD records the signal on the lanes
        that start at the stop line), inf on a lane carrying its own record (past the line)
        or without a light."""
        if self._light_gap is not None:
            return np.asarray(self._light_gap, np.float64)
        lane = self.lanes.lane
        ahead = self.maps.lights.at_end(lane) & (self.light > 0)
        end = self.maps.lane_ends[np.maximum(lane, 0)] if len(self.maps.lane_ends) else \
            np.zeros((len(lane), 2))
        gap = np.hypot(end[:, 0] - self.x, end[:, 1] - self.y)
        return np.where(ahead, gap, np.inf)


class Sensor(ABC):
    """One block of the observation vector (module doc).

    :cvar name: registry name (:func:`register`).
    :cvar scene_frame: the block reads scene-frame coordinates (a translation of the map
        changes it: such a sensor cannot observe a tiled scene, :mod:`magail_sumo.scene.tiling`).
    """

    name: ClassVar[str]
    scene_frame: ClassVar[bool] = False

    def __init__(self, config: "ObservationConfig", maps: SensorMaps) -> None:
        self.config = config
        self.maps = maps

    @classmethod
    @abstractmethod
    def names(cls, config: "ObservationConfig") -> list[str]:
        """Feature names of the block, in order."""

    @classmethod
    def bounds(cls, config: "ObservationConfig") -> tuple[np.ndarray, np.ndarray]:
        """(low, high) float32 bounds of the block's features (default: unbounded)."""
        n = len(cls.names(config))
        return np.full(n, -np.inf, np.float32), np.full(n, np.inf, np.float32)

    @abstractmethod
    def read(self, inp: SensorInput) -> np.ndarray:
        """(A, width) readings of the observing agents (any float dtype; the suite stores
        them as float32)."""


def bounded(n: int, low: float, high: float) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) float32 bounds of ``n`` features that share them."""
    return np.full(n, low, np.float32), np.full(n, high, np.float32)


#: registered sensor classes by name
SENSORS: dict[str, type[Sensor]] = {}

#: layouts by name: the ordered sensor names of the observation vector (``ObservationConfig.
#: layout``; the route command is appended with ``ObservationConfig.command``, the route
#: look-ahead with ``ObservationConfig.route_points``). ``scene_frame``: the MAGAIL4AutoDrive
#: observation, pose and destination in absolute map coordinates.
LAYOUTS: dict[str, tuple[str, ...]] = {
    "ego": ("ego", "lane", "lidar", "side", "lane_line", "light", "destination"),
    "scene_frame": ("scene_pose", "lidar", "side", "lane_line", "light", "scene_destination"),
}

#: deprecated layout names still accepted (:func:`layout_name`): old name -> name now. ``seed``
#: named the predecessor project, where ``seed`` elsewhere is the random seed.
LAYOUT_ALIASES: dict[str, str] = {"seed": "scene_frame"}
#: deprecated sensor names still accepted (:func:`sensor_class`): old name -> name now
SENSOR_ALIASES: dict[str, str] = {"seed_pose": "scene_pose",
                                  "seed_destination": "scene_destination"}
_WARNED: set[tuple[str, str]] = set()  # (kind, old name) already warned about in this process


def _renamed(kind: str, old: str, new: str) -> str:
    """``new``, with a one-line :class:`FutureWarning` the first time in this process that
    ``old`` (a deprecated ``kind`` name) is used (shown by default: users meet it in configs)."""
    if (kind, old) not in _WARNED:
        _WARNED.add((kind, old))
        warnings.warn(f"{kind} {old!r} is deprecated and now called {new!r} (the same values); "
                      f"write {new!r}", FutureWarning, stacklevel=3)
    return new


def layout_name(name: str) -> str:
    """``name``, or the name now of a deprecated layout name (:data:`LAYOUT_ALIASES`; warned
    once per process)."""
    new = LAYOUT_ALIASES.get(name) if isinstance(name, str) else None
    return name if new is None else _renamed("observation layout", name, new)


def register(cls: type[Sensor]) -> type[Sensor]:
    """Class decorator: file a sensor under its ``name`` (a name taken by another class is
    refused)."""
    old = SENSORS.get(cls.name)
    if old is not None and (old.__module__, old.__qualname__) != (cls.__module__, cls.__qualname__):
        raise ValueError(f"sensor name {cls.name!r} is taken by "
                         f"{old.__module__}.{old.__qualname__}")
    SENSORS[cls.name] = cls
    return cls


def register_layout(name: str, sensors: Sequence[str]) -> None:
    """Make ``name`` a valid ``ObservationConfig.layout`` concatenating ``sensors`` in order."""
    LAYOUTS[name] = tuple(sensors)


def sensor_class(name: str) -> type[Sensor]:
    """The sensor registered under ``name`` (a deprecated name, :data:`SENSOR_ALIASES`: the
    sensor it is now, warned once per process); ``KeyError`` naming the known ones otherwise."""
    if name in SENSOR_ALIASES and name not in SENSORS:
        name = _renamed("sensor", name, SENSOR_ALIASES[name])
    try:
        return SENSORS[name]
    except KeyError:
        raise KeyError(f"unknown sensor {name!r} (known: {', '.join(sorted(SENSORS))})") from None


def sensor_order(config: "ObservationConfig") -> tuple[str, ...]:
    """The sensor names of ``config``'s observation vector, in order (its layout, then the
    route command when ``config.command``, the route look-ahead when ``config.route_points``,
    the leader when ``config.leader``, the stop-line distance when ``config.light_gap``, the
    give-way conflict when ``config.give_way``, the path leader when ``config.path_leader``,
    the speed limits when ``config.speed_limit``, the route's standing end when
    ``config.route_stop``, the desired-speed factor when ``config.speed_factor``)."""
    try:
        layout = LAYOUTS[config.layout]
    except KeyError:  # registered in another process (a worker imports what registers it)
        raise KeyError(f"unknown observation layout {config.layout!r} (known: "
                       f"{', '.join(LAYOUTS)})") from None
    return layout + (("command",) if config.command else ()) + \
        (("route",) if config.route_points else ()) + (("leader",) if config.leader else ()) + \
        (("light_gap",) if config.light_gap else ()) + (("give_way",) if config.give_way else ()) \
        + (("path_leader",) if config.path_leader else ()) \
        + (("speed_limit",) if config.speed_limit else ()) \
        + (("route_stop",) if config.route_stop else ()) \
        + (("speed_factor",) if config.speed_factor else ())
