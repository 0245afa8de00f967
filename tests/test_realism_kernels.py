"""The realism feature kernels (numba, broad phases, distinct rows) give bit for bit the values
of the plain all-pairs / all-segments computations they replace."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from converters import load_scene
from magail_sumo.evaluation.realism import interaction, log_replay
from magail_sumo.sensors import road_edge as map_features
from magail_sumo.evaluation.realism.metrics import _row_features, compute_features, distinct_rows
from magail_sumo.evaluation.realism.trajectories import joint_trajectories
from magail_sumo.scene import traffic_light  # the red-light rule's kernels live there

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "data" / "womd" / "637f20cafde22ff8.tfrecord"
f32 = np.float32


@pytest.fixture(scope="module")
def scene():
    return load_scene(SCENE)


def _boxes(rng, B=3, A=9, T=6, spread=12.0, offset=0.0):
    """Random boxes crowded enough to overlap, touch and follow one another."""
    x = (rng.uniform(-spread, spread, (B, A, T)) + offset).astype(f32)
    y = (rng.uniform(-spread, spread, (B, A, T)) - offset).astype(f32)
    h = rng.uniform(-np.pi, np.pi, (B, A, T)).astype(f32)
    h[:, ::3] = h[:, :1]  # equal headings: followed at small lateral overlaps
    length = rng.uniform(0.5, 6.0, (A, T)).astype(f32)
    width = rng.uniform(0.5, 2.5, (A, T)).astype(f32)
    valid = rng.random((B, A, T)) > 0.2
    return x, y, h, length, width, valid


def _nearest_all_pairs(x, y, heading, length, width, valid, n_eval):
    """The all-pairs numpy minimum the kernel replaces."""
    r = np.minimum(length, width) * f32(interaction.CORNER_ROUNDING_FACTOR / 2)
    cl, cw = length - 2 * r, width - 2 * r
    e = slice(0, n_eval)
    d = interaction.signed_box_distance(
        x[:, e, None], y[:, e, None], heading[:, e, None], cl[None, e, None], cw[None, e, None],
        x[:, None], y[:, None], heading[:, None], cl[None, None], cw[None, None])
    d = d - r[None, e, None] - r[None, None]
    ok = valid[:, e, None] & valid[:, None]
    ok[:, np.arange(n_eval), np.arange(n_eval)] = False
    return np.where(ok, d, f32(interaction.EXTREMELY_LARGE_DISTANCE)).min(2)


@pytest.mark.parametrize("seed,spread,offset", [(0, 12.0, 0.0), (1, 4.0, 0.0), (2, 60.0, 0.0),
                                                (3, 12.0, 3e5)])
def test_nearest_object_kernel_equals_all_pairs(seed, spread, offset):
    rng = np.random.default_rng(seed)
    x, y, h, length, width, valid = _boxes(rng, spread=spread, offset=offset)
    for n_eval in (1, 4, x.shape[1]):
        want = _nearest_all_pairs(x, y, h, length, width, valid, n_eval)
        got = interaction.distance_to_nearest_object(x, y, h, length, width, valid, n_eval)
        assert got.dtype == np.float32 and np.array_equal(got, want)
    if spread < 60:
        assert (want < 0).any() and (want == f32(1e10)).any()  # overlaps and lone objects


def test_nearest_object_of_a_lone_object():
    x = np.zeros((1, 1, 3), f32)
    got = interaction.distance_to_nearest_object(x, x, x, np.ones((1, 3), f32),
                                                 np.ones((1, 3), f32), x == 0, 1)
    assert np.array_equal(got, np.full((1, 1, 3), f32(1e10)))


@pytest.mark.parametrize("seed,spread,offset", [(0, 12.0, 0.0), (1, 4.0, 0.0), (2, 12.0, 3e5)])
def test_ttc_kernel_equals_all_pairs(seed, spread, offset):
    rng = np.random.default_rng(seed)
    x, y, h, length, width, valid = _boxes(rng, A=12, spread=spread, offset=offset)
    speed = rng.uniform(0, 15, x.shape).astype(f32)
    speed[:, :, -1] = np.nan  # central differences end in NaN
    for n_eval in (1, 5, x.shape[1]):
        args = (x, y, h, length, width, valid, speed, n_eval)
        want = interaction.time_to_collision_all_pairs(*args)
        got = interaction.time_to_collision(*args)
        assert got.dtype == np.float32 and np.array_equal(got, want, equal_nan=True)
    assert (want < 5).sum() > 5  # followed objects were found


def test_ttc_out_of_range_inputs_use_all_pairs():
    rng = np.random.default_rng(4)
    x, y, h, length, width, valid = _boxes(rng)
    x[0, 0, 0] = f32(1e9)
    speed = rng.uniform(0, 15, x.shape).astype(f32)
    args = (x, y, h, length, width, valid, speed, 3)
    assert np.array_equal(interaction.time_to_collision(*args),
                          interaction.time_to_collision_all_pairs(*args))


def _signed_distance_all_segments(q, segs):
    """Nearest segment by a scan over all segments (first of equal ones), numpy float32."""
    a, b = segs.a, segs.b
    d = b - a
    p = q[:, None, :] - a[None]
    den = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(den != 0, (p[..., 0] * d[:, 0] + p[..., 1] * d[:, 1]) / den, f32(0))
    tc = np.minimum(np.maximum(t, f32(0)), f32(1))
    ox, oy = p[..., 0] - d[:, 0] * tc, p[..., 1] - d[:, 1] * tc
    oz = (p[..., 2] - d[:, 2] * tc) * f32(map_features.Z_STRETCH)
    s = (ox * ox + oy * oy + oz * oz).argmin(1)
    rows = np.arange(len(q))
    t, ox, oy = t[rows, s], ox[rows, s], oy[rows, s]

    def side(k):
        c = ((q[:, 0] - a[k, 0]) * (b[k, 1] - a[k, 1]) - (q[:, 1] - a[k, 1]) * (b[k, 0] - a[k, 0]))
        return np.sign(c).astype(f32)

    sign = side(s)
    for nb, convex, beyond in ((segs.prior, segs.convex_prior, t < 0),
                               (segs.next, segs.convex_next, t > 1)):
        use = beyond & (nb[s] >= 0)
        other = side(np.maximum(nb[s], 0))
        sign = np.where(use, np.where(convex[s], np.maximum(sign, other),
                                      np.minimum(sign, other)), sign)
    return sign * np.sqrt(ox * ox + oy * oy)


def test_road_edge_grid_search_equals_all_segments(scene):
    segs = map_features.road_edge_segments(scene)
    rng = np.random.default_rng(0)
    lo, hi = segs.a.min(0), segs.a.max(0)
    q = rng.uniform(lo - 30, hi + 30, (3000, 3)).astype(f32)
    q[:500] = segs.a[rng.integers(0, len(segs.a), 500)]  # on vertices: equally near segments
    q[500:600, :2] = rng.uniform(-5000, 5000, (100, 2))  # far outside the map
    q[600:700] = q[599]  # repeated points
    q[700:800, 2] = rng.uniform(-50, 50, 100) + lo[2]  # other levels
    q[800:850, :2] = rng.uniform(-1e6, 1e6, (50, 2))  # very far: rounding grows with distance
    got = map_features.signed_distance_to_road_edge(q, segs)
    assert np.array_equal(got, _signed_distance_all_segments(q, segs))


def test_red_light_lane_kernel_equals_argmin(scene):
    lanes = traffic_light.signal_lanes(scene, 91)
    rng = np.random.default_rng(0)
    pts = lanes.points[lanes.seg_valid.any(1)]
    q = rng.uniform(pts.reshape(-1, 2).min(0), pts.reshape(-1, 2).max(0), (300, 2)).astype(f32)
    q[:50] = lanes.points[rng.integers(0, len(lanes.points), 50), 0]
    want, _ = traffic_light._nearest_segment(q, lanes.points[None], lanes.seg_valid[None])
    assert np.array_equal(traffic_light._nearest_lane(q, lanes.points, lanes.seg_valid), want)


def test_features_of_repeated_rows_equal_every_row(scene):
    ro = log_replay(scene, 4)  # four equal rollouts
    jt = joint_trajectories(scene, ro)
    jt = dataclasses.replace(jt, n_eval=len(jt.object_id))
    first, inverse = distinct_rows(jt.x, jt.y, jt.z, jt.heading, jt.valid)
    assert first.tolist() == [0, 1] and inverse.tolist() == [0, 1, 1, 1, 1]
    every = _row_features(scene, jt, np.arange(jt.x.shape[0]), compute_features.__defaults__[0])
    got = compute_features(scene, jt).values
    for name, want in every.items():
        assert got[name].dtype == want.dtype
        assert np.array_equal(got[name], want, equal_nan=want.dtype.kind == "f"), name
