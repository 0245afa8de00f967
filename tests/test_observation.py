"""Observation layout and sensor readings on a real scene against brute-force references."""

from __future__ import annotations

import numpy as np
import pytest

from magail_sumo.sensors.observation import (
    Boxes, EgoState, ObservationConfig, SensorSuite, observation_bounds, observation_names,
)
from test_raycast import reference_distance


def _step(scene, t):
    tr = scene.tracks
    r = np.flatnonzero(tr.valid[:, t])
    boxes = Boxes(tr.x[r, t], tr.y[r, t], tr.heading[r, t].astype(float),
                  tr.length[r, t].astype(float), tr.width[r, t].astype(float))
    a = len(r)
    ego = EgoState(np.arange(a), np.hypot(tr.vx[r, t], tr.vy[r, t]).astype(float),
                   np.zeros((a, 2)), np.stack([tr.x[r, -1], tr.y[r, -1]], 1),
                   tr.heading[r, -1].astype(float))
    return boxes, ego


def test_layouts_and_names():
    assert len(observation_names()) == 113
    scene_frame = ObservationConfig(layout="scene_frame")
    names = observation_names(scene_frame)
    assert len(names) == 108 and names[:5] == ["x", "y", "vx", "vy", "heading"]
    assert names[5] == "lidar_00" and names[85] == "side_00" and names[95] == "lane_line_00"
    assert names[105:] == ["light", "dest_x", "dest_y"]
    low, high = observation_bounds()
    assert low.shape == high.shape == (113,) and high[7] == 30.0
    with pytest.raises(ValueError, match="layout"):
        ObservationConfig(layout="nope")


def test_lidar_block_matches_brute_force(scene_637f):
    suite = SensorSuite(scene_637f)
    boxes, ego = _step(scene_637f, 10)
    obs = suite.observe(boxes, ego, 10)
    names = observation_names()
    lo = names.index("lidar_00")
    lidar = obs[:, lo:lo + 80]
    starts, ends, owner = boxes.edges()
    beams = np.arange(80) * (2 * np.pi / 80)
    ref = np.array([[reference_distance(np.array([boxes.x[i], boxes.y[i]]), boxes.yaw[i] + b, 30.0,
                                        starts[owner != i], ends[owner != i]) for b in beams]
                    for i in range(len(boxes))])
    np.testing.assert_allclose(lidar, ref, atol=1e-4)
    assert (ref < 30.0).mean() > 0.05  # the scene is busy: many beams hit something


def test_observation_blocks_on_real_scene(scene_637f):
    suite = SensorSuite(scene_637f, ObservationConfig(layout="scene_frame"))
    boxes, ego = _step(scene_637f, 20)
    obs = suite.observe(boxes, ego, 20)
    assert obs.shape == (len(boxes), 108) and obs.dtype == np.float32 and np.isfinite(obs).all()
    np.testing.assert_allclose(obs[:, 0], boxes.x, rtol=1e-6)
    assert ((obs[:, 85:95] >= 0) & (obs[:, 85:95] <= 8)).all() and (obs[:, 85:95] < 8).any()
    assert ((obs[:, 95:105] >= 0) & (obs[:, 95:105] <= 3)).all() and (obs[:, 95:105] < 3).any()
    lights = obs[:, 105]
    assert set(np.unique(lights)) <= {0, 1, 2, 3} and (lights > 0).any()
    ego_cfg = SensorSuite(scene_637f).observe(boxes, ego, 20)
    # destination in the ego frame has the same length as in the scene frame
    d_scene = np.hypot(obs[:, 106] - obs[:, 0], obs[:, 107] - obs[:, 1])
    np.testing.assert_allclose(np.hypot(ego_cfg[:, 108], ego_cfg[:, 109]), d_scene, rtol=1e-4,
                               atol=1e-2)
