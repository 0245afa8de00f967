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
====================  ======================================================================

Layout ``"seed"`` (108 values with the defaults, the seed project's vector): position x, y
(scene frame, m) 0–1; velocity vx, vy (scene frame, m/s) 2–3; heading (scene frame, rad) 4;
lidar 5–84; side detector 85–94; lane-line detector 95–104; light 105; destination x, y
(scene frame, m) 106–107 (with ``command: true`` the 3 command values follow).

The current lane is the nearest lane centre line running within 90° of the heading
(:class:`~magail_sumo.sensors.lanes.LaneIndex`); its light comes from
:class:`~magail_sumo.sensors.traffic_lights.LightTable`. :meth:`SensorSuite.observe` runs the
numba kernels of :mod:`magail_sumo.sensors.raycast` over all agents at once.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from magail_sumo.scene import Scene

from .lanes import LaneIndex, LaneQuery
from .raycast import SegmentGrid, box_edges, cast, polyline_segments
from .traffic_lights import LightTable

TWO_PI = 2.0 * np.pi
#: names of the optional route-command one-hot (``ObservationConfig.command``)
COMMAND_NAMES = ["command_left", "command_straight", "command_right"]


@dataclass(frozen=True)
class BeamSpec:
    """A ray sensor: ``beams`` rays over ``fov`` rad centred on the heading, ``range`` m."""

    beams: int
    range: float
    fov: float = TWO_PI

    def offsets(self) -> np.ndarray:
        """(B,) beam angles relative to the heading (rad)."""
        return -0.5 * self.fov + np.arange(self.beams) * (self.fov / max(self.beams, 1)) \
            if self.fov < TWO_PI else np.arange(self.beams) * (TWO_PI / max(self.beams, 1))


@dataclass(frozen=True)
class ObservationConfig:
    """Sensors and layout of the observation vector (see the module doc).

    :param layout: ``"ego"`` (ego-frame quantities) or ``"seed"`` (the seed's 108 values).
    :param lane_cell: grid cell of the lane index (m); lane distances are capped at it.
    :param command: append the route command (one-hot left / straight / right at the next
        junction, :mod:`magail_sumo.sensors.command`) as ``command_left``,
        ``command_straight``, ``command_right``; off by default (the default layout, expert
        data and checkpoints keep their 113 values).
    :param command_lookahead: route distance (m) ahead of the agent at which the command reads
        the route's turn.
    """

    lidar: BeamSpec = field(default_factory=lambda: BeamSpec(80, 30.0))
    side: BeamSpec = field(default_factory=lambda: BeamSpec(10, 8.0))
    lane_line: BeamSpec = field(default_factory=lambda: BeamSpec(10, 3.0))
    layout: str = "ego"
    lane_cell: float = 10.0
    command: bool = False
    command_lookahead: float = 30.0

    def __post_init__(self) -> None:
        if self.layout not in ("ego", "seed"):
            raise ValueError(f"observation layout must be 'ego' or 'seed', got {self.layout!r}")
        if not (np.isfinite(self.command_lookahead) and self.command_lookahead > 0):
            raise ValueError(f"observation command_lookahead must be > 0 m, got "
                             f"{self.command_lookahead!r}")


def observation_names(config: ObservationConfig | None = None) -> list[str]:
    """Name of every entry of the observation vector, in order."""
    cfg = config or ObservationConfig()
    beams = [f"lidar_{j:02d}" for j in range(cfg.lidar.beams)] + \
        [f"side_{j:02d}" for j in range(cfg.side.beams)] + \
        [f"lane_line_{j:02d}" for j in range(cfg.lane_line.beams)]
    command = COMMAND_NAMES if cfg.command else []
    if cfg.layout == "seed":
        return ["x", "y", "vx", "vy", "heading", *beams, "light", "dest_x", "dest_y", *command]
    return ["speed", "prev_accel", "prev_steer", "length", "width", "lane_lateral",
            "lane_heading_error", *beams, "light", "dest_x", "dest_y", "dest_distance",
            "route_cos", "route_sin", *command]


def observation_bounds(config: ObservationConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) float32 bounds of every entry (inf where unbounded)."""
    cfg = config or ObservationConfig()
    names = observation_names(cfg)
    low = np.full(len(names), -np.inf, np.float32)
    high = np.full(len(names), np.inf, np.float32)
    for k, name in enumerate(names):
        for prefix, spec in (("lidar_", cfg.lidar), ("side_", cfg.side), ("lane_line_", cfg.lane_line)):
            if name.startswith(prefix):
                low[k], high[k] = 0.0, spec.range
        if name == "light":
            low[k], high[k] = 0, 3
        elif name in COMMAND_NAMES:
            low[k], high[k] = 0.0, 1.0
        elif name in ("prev_accel", "prev_steer", "route_cos", "route_sin"):
            low[k], high[k] = -1.0, 1.0
        elif name in ("length", "width", "dest_distance"):
            low[k] = 0.0
        elif name in ("lane_heading_error", "heading"):
            low[k], high[k] = -np.pi, np.pi
    return low, high


@dataclass(frozen=True)
class Boxes:
    """Oriented boxes of every road user in the sensor world at one step (N,) arrays.

    :param x, y: box centre (m, scene frame). :param yaw: heading (rad, scene frame).
    :param length, width: box size (m).
    """

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    length: np.ndarray
    width: np.ndarray

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
    """

    index: np.ndarray
    speed: np.ndarray
    prev_action: np.ndarray
    destination: np.ndarray
    destination_yaw: np.ndarray
    command: np.ndarray | None = None


class SensorSuite:
    """Static sensor geometry of one scene (built once) and the observation of every agent."""

    def __init__(self, scene: Scene, config: ObservationConfig | None = None) -> None:
        self.config = cfg = config or ObservationConfig()
        rm = scene.roadmap
        self.edges = SegmentGrid.build(*polyline_segments([e.polyline for e in rm.road_edges]),
                                       cell=max(cfg.side.range, 1.0))
        self.lines = SegmentGrid.build(*polyline_segments([l.polyline for l in rm.road_lines]),
                                       cell=max(cfg.lane_line.range, 1.0))
        self.lanes = LaneIndex.build(rm.lanes, cell=cfg.lane_cell)
        self.lights = LightTable.build(scene)
        self.names = observation_names(cfg)
        self.size = len(self.names)
        self._offsets = [s.offsets() for s in (cfg.lidar, cfg.side, cfg.lane_line)]

    def lane_query(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> LaneQuery:
        """Current lane (see :class:`LaneQuery`) of A poses."""
        return self.lanes.query(x, y, yaw)

    #: Above this many boxes the lidar buckets box edges in a grid first (per step): brute force
    #: tests every agent against every edge (O(A·N)); on a 380-vehicle city step the grid
    #: halves the lidar time, on a 50-box scene brute force is as fast.
    GRID_LIDAR_MIN_BOXES = 128

    def lidar(self, boxes: Boxes, index: np.ndarray) -> np.ndarray:
        """(A, B) lidar readings (m) of the boxes at rows ``index`` against all other boxes."""
        spec = self.config.lidar
        origins = np.stack([boxes.x[index], boxes.y[index]], axis=1)
        angles = np.asarray(boxes.yaw, np.float64)[index, None] + self._offsets[0][None, :]
        starts, ends, owner = boxes.edges()
        agent = np.asarray(index, np.int64)
        if len(boxes) >= self.GRID_LIDAR_MIN_BOXES:
            grid = SegmentGrid.build(starts, ends, cell=max(spec.range, 1.0))
            return grid.cast(origins, angles, spec.range, owner, agent)
        return cast(origins, angles, spec.range, starts, ends, owner, agent)

    def observe(self, boxes: Boxes, ego: EgoState, step: int,
                lanes: LaneQuery | None = None, light: np.ndarray | None = None) -> np.ndarray:
        """(A, D) float32 observations of the agents at log step ``step`` (layout: module doc).

        :param lanes: the agents' :meth:`lane_query` when already computed this step.
        :param light: (A,) current-lane light codes (0 none, 1 green, 2 yellow, 3 red) from a
            live source (a SUMO run without a recording); default: the recorded signal table.
        """
        cfg = self.config
        idx = np.asarray(ego.index, np.int64)
        a = idx.shape[0]
        if a == 0:
            return np.zeros((0, self.size), np.float32)
        x, y = boxes.x[idx], boxes.y[idx]
        yaw = np.asarray(boxes.yaw, np.float64)[idx]
        origins = np.stack([x, y], axis=1)
        lidar = self.lidar(boxes, idx)
        side = self.edges.cast(origins, yaw[:, None] + self._offsets[1][None, :], cfg.side.range)
        line = self.lines.cast(origins, yaw[:, None] + self._offsets[2][None, :],
                               cfg.lane_line.range)
        lq = lanes if lanes is not None else self.lane_query(x, y, yaw)
        light = (self.lights.lookup(step, lq.lane) if light is None else
                 np.asarray(light)).astype(np.float64)
        dx, dy = ego.destination[:, 0] - x, ego.destination[:, 1] - y
        if cfg.layout == "seed":
            cols = [x, y, ego.speed * np.cos(yaw), ego.speed * np.sin(yaw), yaw, lidar, side, line,
                    light, ego.destination[:, 0], ego.destination[:, 1]]
        else:
            c, s = np.cos(yaw), np.sin(yaw)
            rel = ego.destination_yaw - yaw
            cols = [ego.speed, ego.prev_action[:, 0], ego.prev_action[:, 1], boxes.length[idx],
                    boxes.width[idx], lq.lateral, lq.heading_error, lidar, side, line, light,
                    c * dx + s * dy, -s * dx + c * dy, np.hypot(dx, dy), np.cos(rel), np.sin(rel)]
        if cfg.command:
            if ego.command is None:
                from .command import STRAIGHT, one_hot

                cols.append(one_hot(np.full(a, STRAIGHT)))
            else:
                cols.append(ego.command)
        out = np.empty((a, self.size), np.float32)
        k = 0
        for col in cols:  # a fixed handful of column blocks, not a per-agent loop
            col = np.asarray(col).reshape(a, -1)
            out[:, k:k + col.shape[1]] = col
            k += col.shape[1]
        return out
