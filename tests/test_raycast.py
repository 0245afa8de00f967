"""Ray casting kernels against a brute-force, per-ray reference (agreement to 1e-4 m)."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import WOMD_DIR
from converters import load_scene
from magail_sumo.sensors.raycast import SegmentGrid, box_edges, cast, polyline_segments


def reference_distance(origin, angle, max_range, starts, ends) -> float:
    """Per-ray, per-segment loop solving the 2x2 system origin + t·d = a + u·(b - a)."""
    d = np.array([np.cos(angle), np.sin(angle)])
    best = max_range
    # skip segments whose bounding box is out of reach (keeps the loop short on real maps)
    near = (np.minimum(starts, ends) <= origin + max_range).all(1) & \
           (np.maximum(starts, ends) >= origin - max_range).all(1)
    for a, b in zip(starts[near], ends[near]):
        m = np.array([[d[0], a[0] - b[0]], [d[1], a[1] - b[1]]])
        if abs(np.linalg.det(m)) < 1e-12:
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


@pytest.mark.parametrize("seed", range(5))
def test_random_segments_agree_with_reference(seed):
    rng = np.random.default_rng(seed)
    origins = rng.uniform(-20, 20, (6, 2))
    angles = rng.uniform(-np.pi, np.pi, (6, 24))
    starts = rng.uniform(-30, 30, (40, 2))
    ends = starts + rng.normal(0, 6, (40, 2))
    got = cast(origins, angles, 15.0, starts, ends)
    grid = SegmentGrid.build(starts, ends, cell=15.0).cast(origins, angles, 15.0)
    ref = np.array([[reference_distance(origins[i], angles[i, j], 15.0, starts, ends)
                     for j in range(24)] for i in range(6)])
    np.testing.assert_allclose(got, ref, atol=1e-4)
    np.testing.assert_allclose(grid, ref, atol=1e-4)
    assert (ref < 15.0).sum() > 10  # the case actually hits things


def test_oriented_boxes_own_box_and_grazing_cases():
    edges = box_edges(np.array([[10.0, 0.0], [0.0, 0.0]]), np.array([[2.0, 1.0], [2.0, 1.0]]),
                      np.array([0.0, 0.0]))
    starts, ends = edges[:, :, 0].reshape(-1, 2), edges[:, :, 1].reshape(-1, 2)
    owner = np.repeat([0, 1], 4)
    angles = np.array([[0.0, np.arctan2(1.0, 8.0), np.pi, np.arctan2(1.0, 12.0)]])
    got = cast(np.zeros((1, 2)), angles, 30.0, starts, ends, owner, np.array([1]))
    assert got[0, 0] == pytest.approx(8.0)  # rear face of the box ahead, own box ignored
    assert got[0, 1] == pytest.approx(np.hypot(8.0, 1.0))  # through the rear-left corner
    assert got[0, 2] == 30.0  # pointing away
    assert got[0, 3] == pytest.approx(np.hypot(8.0, 8.0 / 12.0))  # enters through the rear face
    # without the exclusion the agent sees its own box from inside
    assert cast(np.zeros((1, 2)), angles, 30.0, starts, ends)[0, 0] == pytest.approx(2.0)
    # a ray running exactly along an edge line hits the edge's near end point
    along = cast(np.array([[0.0, 1.0]]), np.array([[0.0]]), 30.0, starts[:4], ends[:4])
    assert along[0, 0] == pytest.approx(8.0)


@pytest.mark.parametrize("cell", [2.5, 6.0, 15.0, 40.0])
def test_grid_of_any_cell_size_agrees_with_reference(cell):
    """Cells smaller than the range (several rings visited, the far corners skipped) or larger;
    long segments listed in many visited cells count once and still give the nearest hit."""
    rng = np.random.default_rng(7)
    origins = rng.uniform(-20, 20, (8, 2))
    b = 30
    angles = rng.uniform(-np.pi, np.pi, (8, 1)) + np.arange(b)[None] * (2 * np.pi / b)
    starts = rng.uniform(-35, 35, (50, 2))
    ends = starts + rng.normal(0, 6, (50, 2))
    starts[:5], ends[:5] = rng.uniform(-40, 40, (5, 2)), rng.uniform(-40, 40, (5, 2))  # long
    got = SegmentGrid.build(starts, ends, cell=cell).cast(origins, angles, 15.0)
    irregular = angles + rng.uniform(0, 0.05, angles.shape)  # the per-beam kernel
    got_irr = SegmentGrid.build(starts, ends, cell=cell).cast(origins, irregular, 15.0)
    for a, out in ((angles, got), (irregular, got_irr)):
        ref = np.array([[reference_distance(origins[i], a[i, j], 15.0, starts, ends)
                         for j in range(b)] for i in range(8)])
        np.testing.assert_allclose(out, ref, atol=1e-4)
        assert (ref < 15.0).sum() > 20


def test_real_scene_lidar_and_road_edges_against_reference():
    scene = load_scene(WOMD_DIR / "637f20cafde22ff8.tfrecord")
    tr = scene.tracks
    t = scene.current_time_index
    idx = np.flatnonzero(tr.valid[:, t])
    centers = np.stack([tr.x[idx, t], tr.y[idx, t]], axis=1)
    half = np.stack([tr.length[idx, t], tr.width[idx, t]], axis=1) / 2
    heading = tr.heading[idx, t].astype(np.float64)
    edges = box_edges(centers, half, heading)
    starts, ends = edges[:, :, 0].reshape(-1, 2), edges[:, :, 1].reshape(-1, 2)
    owner = np.repeat(np.arange(len(idx)), 4)
    angles = heading[:, None] + np.linspace(0, 2 * np.pi, 80, endpoint=False)[None]
    got = cast(centers, angles, 30.0, starts, ends, owner, np.arange(len(idx)))
    for k in range(0, len(idx), 7):
        others = owner != k
        ref = [reference_distance(centers[k], a, 30.0, starts[others], ends[others]) for a in angles[k]]
        np.testing.assert_allclose(got[k], ref, atol=1e-4)
    assert (got < 30.0).mean() > 0.2
    rs, re_ = polyline_segments([e.polyline for e in scene.roadmap.road_edges])
    side = heading[:, None] + np.linspace(0, 2 * np.pi, 10, endpoint=False)[None]
    grid = SegmentGrid.build(rs, re_, cell=30.0)
    got = grid.cast(centers, side, 8.0)
    for k in range(0, len(idx), 3):
        ref = [reference_distance(centers[k], a, 8.0, rs, re_) for a in side[k]]
        np.testing.assert_allclose(got[k], ref, atol=1e-4)
    assert (got < 8.0).any()


@pytest.mark.parametrize("seed, fov", [(0, 2 * np.pi), (1, 2 * np.pi), (2, np.pi / 2), (3, 3.0)])
def test_evenly_spaced_beams_use_the_angular_window_and_agree(seed, fov):
    """Evenly spaced beams take the windowed kernel; results equal the per-ray reference."""
    from magail_sumo.sensors.raycast import _uniform

    rng = np.random.default_rng(seed)
    origins = rng.uniform(-10, 10, (5, 2))
    starts = rng.uniform(-20, 20, (60, 2))
    ends = starts + rng.normal(0, 5, (60, 2))
    starts[0], ends[0] = origins[0] - (1.0, 0.0), origins[0] + (1.0, 0.0)  # origin on a segment
    b = 36
    step = fov / b if fov >= 2 * np.pi else fov / (b - 1)
    angles = rng.uniform(-np.pi, np.pi, (5, 1)) + np.arange(b)[None] * step
    assert _uniform(angles)[0] > 0
    got = cast(origins, angles, 12.0, starts, ends)
    grid = SegmentGrid.build(starts, ends, cell=12.0).cast(origins, angles, 12.0)
    ref = np.array([[reference_distance(origins[i], angles[i, j], 12.0, starts, ends)
                     for j in range(b)] for i in range(5)])
    np.testing.assert_allclose(got, ref, atol=1e-4)
    np.testing.assert_allclose(grid, ref, atol=1e-4)


def test_grid_with_owners_equals_brute_force_on_many_boxes():
    """The lidar's grid path (many boxes) gives the brute-force readings, own box excluded."""
    rng = np.random.default_rng(0)
    n = 300
    centre = rng.uniform(0, 300, (n, 2))
    yaw = rng.uniform(-np.pi, np.pi, n)
    edges = box_edges(centre, np.stack([rng.uniform(1.5, 3, n), rng.uniform(0.8, 1.2, n)], 1), yaw)
    starts, ends = edges[:, :, 0].reshape(-1, 2), edges[:, :, 1].reshape(-1, 2)
    owner = np.repeat(np.arange(n), 4)
    angles = yaw[:, None] + np.arange(80) * (2 * np.pi / 80)
    brute = cast(centre, angles, 30.0, starts, ends, owner, np.arange(n))
    grid = SegmentGrid.build(starts, ends, cell=30.0).cast(centre, angles, 30.0, owner, np.arange(n))
    np.testing.assert_array_equal(grid, brute)
    assert 0.1 < (brute < 30.0).mean() < 0.9
