"""Sensor units: registering a sensor, layouts, and the unit suite's observations bit-identical to
the monolithic observation code it replaced (kept below as the reference) on the real scenes."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import WOMD_DIR
from converters import load_scene
from magail_sumo.config import from_dict, to_dict
from magail_sumo.env.config import EnvConfig
from magail_sumo.sensors import base
from magail_sumo.sensors.base import Sensor, SensorInput, bounded, register, register_layout
from magail_sumo.sensors.command import STRAIGHT, RouteCommands, one_hot
from magail_sumo.sensors.lanes import LaneIndex
from magail_sumo.sensors.observation import (
    COMMAND_NAMES, BeamSpec, Boxes, EgoState, ObservationConfig, SensorSuite, observation_bounds,
    observation_names,
)
from magail_sumo.sensors.raycast import SegmentGrid, cast, polyline_segments
from magail_sumo.sensors.traffic_lights import NO_LIGHTS, LightTable

CONFIGS = {
    "ego": ObservationConfig(),
    "scene_frame": ObservationConfig(layout="scene_frame"),
    "command": ObservationConfig(command=True),
    "scene_frame_command": ObservationConfig(layout="scene_frame", command=True,
                                             command_lookahead=12.0),
    "beams": ObservationConfig(lidar=BeamSpec(17, 25.0, np.pi), side=BeamSpec(5, 6.0, 1.5),
                               lane_line=BeamSpec(3, 2.0), lane_cell=5.0),
}


# --------------------------------------------------------------------------- the old code path
def reference_names(cfg: ObservationConfig) -> list[str]:
    """``observation_names`` as written before the sensor units (the scene-frame and ego
    layouts)."""
    beams = [f"lidar_{j:02d}" for j in range(cfg.lidar.beams)] + \
        [f"side_{j:02d}" for j in range(cfg.side.beams)] + \
        [f"lane_line_{j:02d}" for j in range(cfg.lane_line.beams)]
    command = COMMAND_NAMES if cfg.command else []
    if cfg.layout == "scene_frame":
        return ["x", "y", "vx", "vy", "heading", *beams, "light", "dest_x", "dest_y", *command]
    return ["speed", "prev_accel", "prev_steer", "length", "width", "lane_lateral",
            "lane_heading_error", *beams, "light", "dest_x", "dest_y", "dest_distance",
            "route_cos", "route_sin", *command]


def reference_bounds(cfg: ObservationConfig) -> tuple[np.ndarray, np.ndarray]:
    """``observation_bounds`` as written before the sensor units."""
    names = reference_names(cfg)
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


class ReferenceSuite:
    """``SensorSuite`` as written before the sensor units (one ``observe`` over a scene)."""

    def __init__(self, scene, cfg: ObservationConfig) -> None:
        rm = scene.roadmap
        self.cfg = cfg
        self.edges = SegmentGrid.build(*polyline_segments([e.polyline for e in rm.road_edges]),
                                       cell=max(cfg.side.range, 1.0))
        self.lines = SegmentGrid.build(*polyline_segments([l.polyline for l in rm.road_lines]),
                                       cell=max(cfg.lane_line.range, 1.0))
        self.lanes = LaneIndex.build(rm.lanes, cell=cfg.lane_cell)
        self.lights = LightTable.build(scene)
        self.size = len(reference_names(cfg))
        self.offsets = [s.offsets() for s in (cfg.lidar, cfg.side, cfg.lane_line)]

    def lidar(self, boxes: Boxes, index: np.ndarray) -> np.ndarray:
        spec = self.cfg.lidar
        origins = np.stack([boxes.x[index], boxes.y[index]], axis=1)
        angles = np.asarray(boxes.yaw, np.float64)[index, None] + self.offsets[0][None, :]
        starts, ends, owner = boxes.edges()
        agent = np.asarray(index, np.int64)
        if len(boxes) >= 128:
            grid = SegmentGrid.build(starts, ends, cell=max(spec.range, 1.0))
            return grid.cast(origins, angles, spec.range, owner, agent)
        return cast(origins, angles, spec.range, starts, ends, owner, agent)

    def observe(self, boxes, ego, step, lanes=None, light=None) -> np.ndarray:
        cfg = self.cfg
        idx = np.asarray(ego.index, np.int64)
        a = idx.shape[0]
        if a == 0:
            return np.zeros((0, self.size), np.float32)
        x, y = boxes.x[idx], boxes.y[idx]
        yaw = np.asarray(boxes.yaw, np.float64)[idx]
        origins = np.stack([x, y], axis=1)
        lidar = self.lidar(boxes, idx)
        side = self.edges.cast(origins, yaw[:, None] + self.offsets[1][None, :], cfg.side.range)
        line = self.lines.cast(origins, yaw[:, None] + self.offsets[2][None, :],
                               cfg.lane_line.range)
        lq = lanes if lanes is not None else self.lanes.query(x, y, yaw)
        light = (self.lights.lookup(step, lq.lane) if light is None else
                 np.asarray(light)).astype(np.float64)
        dx, dy = ego.destination[:, 0] - x, ego.destination[:, 1] - y
        if cfg.layout == "scene_frame":
            cols = [x, y, ego.speed * np.cos(yaw), ego.speed * np.sin(yaw), yaw, lidar, side, line,
                    light, ego.destination[:, 0], ego.destination[:, 1]]
        else:
            c, s = np.cos(yaw), np.sin(yaw)
            rel = ego.destination_yaw - yaw
            cols = [ego.speed, ego.prev_action[:, 0], ego.prev_action[:, 1], boxes.length[idx],
                    boxes.width[idx], lq.lateral, lq.heading_error, lidar, side, line, light,
                    c * dx + s * dy, -s * dx + c * dy, np.hypot(dx, dy), np.cos(rel), np.sin(rel)]
        if cfg.command:
            cols.append(one_hot(np.full(a, STRAIGHT)) if ego.command is None else ego.command)
        out = np.empty((a, self.size), np.float32)
        k = 0
        for col in cols:
            col = np.asarray(col).reshape(a, -1)
            out[:, k:k + col.shape[1]] = col
            k += col.shape[1]
        return out


# --------------------------------------------------------------------------- inputs
def _inputs(scene, t: int, every: int = 1, crowd: bool = False, commands=None, seed: int = 0):
    """Boxes of the log's valid road users at step ``t`` (copies shifted 3.3 m apart up to
    more than 128 boxes with ``crowd``: the grid lidar) and an ego state of every ``every``-th
    one (random previous actions, the log's last state as destination)."""
    tr = scene.tracks
    tt = min(t, tr.valid.shape[1] - 1)
    r = np.flatnonzero(tr.valid[:, tt])
    cols = [tr.x[r, tt].astype(float), tr.y[r, tt].astype(float), tr.heading[r, tt].astype(float),
            tr.length[r, tt].astype(float), tr.width[r, tt].astype(float)]
    if crowd:
        reps = 140 // max(len(r), 1) + 1
        cols = [np.concatenate([v + (3.3 * j if i < 2 else 0.0) for j in range(reps)])
                for i, v in enumerate(cols)]
    boxes = Boxes(*cols)
    sel = np.arange(len(r))[::every]
    rows = r[sel]
    cmd = None if commands is None else commands.commands(rows, tr.x[rows, tt], tr.y[rows, tt])
    ego = EgoState(sel, np.hypot(tr.vx[rows, tt], tr.vy[rows, tt]).astype(float),
                   np.random.default_rng(seed).uniform(-1, 1, (sel.size, 2)),
                   np.stack([tr.x[rows, -1], tr.y[rows, -1]], 1), tr.heading[rows, -1].astype(float),
                   cmd)
    return boxes, ego


def _same_bits(a: np.ndarray, b: np.ndarray) -> None:
    assert a.dtype == b.dtype and a.shape == b.shape
    assert a.tobytes() == b.tobytes(), f"{np.count_nonzero(a != b)} values differ"


# --------------------------------------------------------------------------- tests
@pytest.mark.parametrize("name", list(CONFIGS))
def test_names_and_bounds_as_before(name):
    cfg = CONFIGS[name]
    assert observation_names(cfg) == reference_names(cfg)
    for got, want in zip(observation_bounds(cfg), reference_bounds(cfg)):
        _same_bits(got, want)


@pytest.mark.parametrize("sid", ["637f20cafde22ff8", "2831b6fde0420b0d", "850c48d8bbfa008f"])
def test_observations_bit_identical_to_the_old_suite(sid):
    scene = load_scene(WOMD_DIR / f"{sid}.tfrecord")
    t_steps = scene.num_steps
    routes = RouteCommands.build(scene.tracks, 30.0)
    for name, cfg in CONFIGS.items():
        new, old = SensorSuite(scene, cfg), ReferenceSuite(scene, cfg)
        cmd = routes if cfg.command else None
        for t, every, crowd in ((0, 1, False), (10, 2, False), (t_steps // 2, 1, True),
                                (t_steps + 5, 1, False)):
            boxes, ego = _inputs(scene, t, every, crowd, cmd if t else None, seed=t)
            _same_bits(new.observe(boxes, ego, t), old.observe(boxes, ego, t))
        # the caller's lane query, a live light, no observing agent
        boxes, ego = _inputs(scene, 10, commands=cmd)
        lq = new.lane_query(boxes.x, boxes.y, boxes.yaw)
        live = np.random.default_rng(1).integers(0, 4, len(boxes))
        _same_bits(new.observe(boxes, ego, 10, lq, live), old.observe(boxes, ego, 10, lq, live))
        none = EgoState(np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2)),
                        np.zeros(0))
        _same_bits(new.observe(boxes, none, 3), old.observe(boxes, none, 3))
    # built from the road map and the recorded lights, as the envs do
    cfg = CONFIGS["scene_frame"]
    boxes, ego = _inputs(scene, 12)
    _same_bits(SensorSuite.from_map(scene.roadmap, LightTable.build(scene), cfg).observe(
        boxes, ego, 12), ReferenceSuite(scene, cfg).observe(boxes, ego, 12))


def test_map_without_recorded_lights(scene_637f):
    """A map without a light source (a SUMO city) reads light 0, or the live light passed."""
    suite = SensorSuite.from_map(scene_637f.roadmap, None, ObservationConfig())
    assert suite.lights is NO_LIGHTS
    boxes, ego = _inputs(scene_637f, 20)
    k = suite.names.index("light")
    assert (suite.observe(boxes, ego, 20)[:, k] == 0).all()
    recorded = SensorSuite(scene_637f).observe(boxes, ego, 20)
    assert (recorded[:, k] > 0).any()  # the scene has lights: the table is not what is read
    live = np.arange(len(boxes)) % 4
    obs = suite.observe(boxes, ego, 20, light=live)
    np.testing.assert_array_equal(obs[:, k], live)
    _same_bits(np.delete(obs, k, axis=1), np.delete(recorded, k, axis=1))


class _Toy(Sensor):
    """Test sensor: twice the speed, and the number of road edges of the map."""

    name = "toy_test"

    @classmethod
    def names(cls, config):
        return ["toy_speed2", "toy_edges"]

    @classmethod
    def bounds(cls, config):
        return bounded(2, -1.0, 7.0)

    def __init__(self, config, maps):
        super().__init__(config, maps)
        self.edges = len(maps.roadmap.road_edges)

    def read(self, inp: SensorInput):
        return np.stack([2.0 * inp.ego.speed, np.full(len(inp), self.edges)], axis=1)


@pytest.fixture
def registries():
    """Registries a test may add to; restored afterwards."""
    base.sensor_class("ego")  # the built-in units registered first
    saved = dict(base.SENSORS), dict(base.LAYOUTS)
    yield
    for registry, old in zip((base.SENSORS, base.LAYOUTS), saved):
        registry.clear()
        registry.update(old)


def test_registered_sensor_is_concatenated(scene_637f, registries):
    register(_Toy)
    order = (*base.sensor_order(ObservationConfig()), "toy_test")
    names = observation_names(sensors=order)
    assert names == observation_names() + ["toy_speed2", "toy_edges"]
    low, high = observation_bounds(sensors=order)
    _same_bits(low[:113], observation_bounds()[0])
    assert low[113:].tolist() == [-1.0, -1.0] and high[113:].tolist() == [7.0, 7.0]
    suite = SensorSuite(scene_637f, sensors=order)
    assert suite.names == names and suite.size == 115
    boxes, ego = _inputs(scene_637f, 30)
    obs = suite.observe(boxes, ego, 30)
    _same_bits(obs[:, :113], SensorSuite(scene_637f).observe(boxes, ego, 30))
    np.testing.assert_array_equal(obs[:, 113], (2.0 * ego.speed).astype(np.float32))
    assert (obs[:, 114] == len(scene_637f.roadmap.road_edges)).all()
    # a registered layout is a valid config layout
    register_layout("toy_layout", ("toy_test", "light"))
    cfg = ObservationConfig(layout="toy_layout")
    assert observation_names(cfg) == ["toy_speed2", "toy_edges", "light"]
    obs = SensorSuite(scene_637f, cfg).observe(boxes, ego, 30)
    _same_bits(obs[:, 2], SensorSuite(scene_637f).observe(boxes, ego, 30)[:, 107])


def test_refused_sensor_set_ups(scene_637f, registries):
    with pytest.raises(ValueError,
                       match="layout must be one of 'ego', 'scene_frame', got 'nope'"):
        ObservationConfig(layout="nope")
    with pytest.raises(KeyError, match="unknown sensor 'nope'.*lidar"):
        observation_names(sensors=("ego", "nope"))
    with pytest.raises(ValueError, match="named twice: light"):
        observation_names(sensors=("light", "lidar", "light"))

    class Taken(_Toy):
        name = "lidar"

    with pytest.raises(ValueError, match="'lidar' is taken by .*units.lidar.Lidar"):
        register(Taken)

    class Wide(_Toy):
        name = "toy_wide"

        def read(self, inp):
            return np.zeros((len(inp), 3))

    register(Wide)
    boxes, ego = _inputs(scene_637f, 5)
    with pytest.raises(ValueError, match="'toy_wide' read 3 values per agent but declares 2"):
        SensorSuite(scene_637f, sensors=("toy_wide",)).observe(boxes, ego, 5)


def test_seed_layout_is_a_deprecated_name_of_scene_frame(scene_637f, monkeypatch):
    """``seed`` named the predecessor project (MAGAIL4AutoDrive) in a codebase where ``seed`` is
    the random seed: the layout is now ``scene_frame``. The old name still loads, as the same
    config (the new name held), with one ``FutureWarning`` per process, so configs, checkpoints
    and expert data recorded with it load, match and observe as before."""
    monkeypatch.setattr(base, "_WARNED", set())
    with pytest.warns(FutureWarning) as caught:
        old = ObservationConfig(layout="seed")
        again = from_dict(ObservationConfig, {"layout": "seed", "command": True})
    renamed = [str(w.message) for w in caught if issubclass(w.category, FutureWarning)]
    assert renamed == ["observation layout 'seed' is deprecated and now called 'scene_frame' "
                       "(the same values); write 'scene_frame'"]  # once, one line
    new = ObservationConfig(layout="scene_frame")
    assert old == new and old.layout == "scene_frame" and to_dict(old) == to_dict(new)
    assert again == ObservationConfig(layout="scene_frame", command=True)
    assert observation_names(old) == observation_names(new)  # expert data of either matches
    assert len(observation_names(old)) == 108
    boxes, ego = _inputs(scene_637f, 20)
    _same_bits(SensorSuite(scene_637f, old).observe(boxes, ego, 20),
               SensorSuite(scene_637f, new).observe(boxes, ego, 20))
    # a checkpoint's env recorded with the old name is the env of the new one, setting for
    # setting (what evaluation compares a checkpoint's env with)
    trained = from_dict(EnvConfig, {"observation": {"layout": "seed"}})
    assert to_dict(trained) == to_dict(EnvConfig(observation=new))
    # the old sensor names too (a custom layout or suite naming them)
    with pytest.warns(FutureWarning, match="sensor 'seed_pose' is deprecated.*'scene_pose'"):
        assert base.sensor_class("seed_pose") is base.sensor_class("scene_pose")
    with pytest.warns(FutureWarning, match="sensor 'seed_destination' is deprecated"):
        assert observation_names(sensors=("seed_destination",)) == ["dest_x", "dest_y"]
