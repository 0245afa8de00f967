"""Vectorised ray casting against a brute-force, per-ray reference (agreement to 1e-4 m)."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import WOMD_DIR
from converters import load_scene
from magail_sumo.sensors.raycast import box_edges, candidate_pairs, cast


def reference_distance(origin, angle, max_range, starts, ends) -> float:
    """Per-ray, per-segment loop solving the 2x2 system origin + t·d = a + u·(b - a)."""
    d = np.array([np.cos(angle), np.sin(angle)])
    best = max_range
    for a, b in zip(starts, ends):
        m = np.array([[d[0], a[0] - b[0]], [d[1], a[1] - b[1]]])
        if abs(np.linalg.det(m)) < 1e-12:
            # parallel: hits only if collinear, at the nearest end point ahead of the origin
            rel_a, rel_b = a - origin, b - origin
            if abs(rel_a[0] * d[1] - rel_a[1] * d[0]) > 1e-9:
                continue
            ts = sorted([rel_a @ d, rel_b @ d])
            t = ts[0] if ts[0] >= 0 else (0.0 if ts[1] >= 0 else None)
        else:
            t, u = np.linalg.solve(m, a - origin)
            if not (t >= 0 and 0 <= u <= 1):
                continue
        if t is not None and t <= best:
            best = t
    return best


def run_vectorised(origins, angles, max_range, starts, ends):
    g, s = candidate_pairs(origins, starts, ends, max_range)
    return cast(origins, angles, max_range, starts, ends, g, s)


@pytest.mark.parametrize("seed", range(5))
def test_random_segments_agree_with_reference(seed):
    rng = np.random.default_rng(seed)
    origins = rng.uniform(-20, 20, (6, 2))
    angles = rng.uniform(-np.pi, np.pi, (6, 24))
    starts = rng.uniform(-30, 30, (40, 2))
    ends = starts + rng.normal(0, 6, (40, 2))
    got = run_vectorised(origins, angles, 15.0, starts, ends)
    for i in range(6):
        for j in range(24):
            assert got[i, j] == pytest.approx(
                reference_distance(origins[i], angles[i, j], 15.0, starts, ends), abs=1e-4)
    assert (got < 15.0).sum() > 10  # the case actually hits things


def test_oriented_boxes_and_grazing_cases():
    edges = box_edges(np.array([[10.0, 0.0]]), np.array([[2.0, 1.0]]), np.array([0.0]))
    starts, ends = edges[:, :, 0].reshape(-1, 2), edges[:, :, 1].reshape(-1, 2)
    origins = np.zeros((1, 2))
    angles = np.array([[0.0, np.arctan2(1.0, 8.0), np.pi, np.arctan2(1.0, 12.0)]])
    got = run_vectorised(origins, angles, 30.0, starts, ends)
    assert got[0, 0] == pytest.approx(8.0)  # rear face of the box
    assert got[0, 1] == pytest.approx(np.hypot(8.0, 1.0))  # through the rear-left corner
    assert got[0, 2] == 30.0  # pointing away
    assert got[0, 3] == pytest.approx(np.hypot(8.0, 8.0 / 12.0))  # enters through the rear face
    # a ray running exactly along an edge line hits the edge's near end point
    along = run_vectorised(np.array([[0.0, 1.0]]), np.array([[0.0]]), 30.0, starts, ends)
    assert along[0, 0] == pytest.approx(8.0)


def test_real_scene_lidar_against_reference():
    scene = load_scene(WOMD_DIR / "637f20cafde22ff8.tfrecord")
    tr = scene.tracks
    t = scene.current_time_index
    idx = np.flatnonzero(tr.valid[:, t])
    centers = np.stack([tr.x[idx, t], tr.y[idx, t]], axis=1)
    half = np.stack([tr.length[idx, t], tr.width[idx, t]], axis=1) / 2
    edges = box_edges(centers, half, tr.heading[idx, t].astype(np.float64))
    starts, ends = edges[:, :, 0].reshape(-1, 2), edges[:, :, 1].reshape(-1, 2)
    agents = idx[:8]
    origins = centers[:8]
    angles = tr.heading[agents, t][:, None] + np.linspace(0, 2 * np.pi, 80, endpoint=False)[None]
    # exclude each agent's own box: cast per agent against the others
    for k in range(len(agents)):
        others = np.ones(len(idx), bool)
        others[k] = False
        s_, e_ = edges[others, :, 0].reshape(-1, 2), edges[others, :, 1].reshape(-1, 2)
        got = run_vectorised(origins[k:k + 1], angles[k:k + 1], 30.0, s_, e_)
        ref = [reference_distance(origins[k], a, 30.0, s_, e_) for a in angles[k]]
        np.testing.assert_allclose(got[0], ref, atol=1e-4)
    assert starts.shape[0] == 4 * len(idx)
    # road edges of the real map
    road = [e.polyline[:, :2] for e in scene.roadmap.road_edges]
    rs = np.concatenate([p[:-1] for p in road])
    re_ = np.concatenate([p[1:] for p in road])
    side = np.linspace(0, 2 * np.pi, 10, endpoint=False)
    side_angles = tr.heading[agents, t][:, None] + side[None]
    got = run_vectorised(origins, side_angles, 8.0, rs, re_)
    for k in range(len(agents)):
        ref = [reference_distance(origins[k], a, 8.0, rs, re_) for a in side_angles[k]]
        np.testing.assert_allclose(got[k], ref, atol=1e-4)
