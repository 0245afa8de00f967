"""The nearest-lane index answers as a scan of every lane segment would, whatever its grid.

Real scenes (the bundled WOMD, ScenarioNet and nuScenes files): every recorded pose, the same
poses moved a few metres with random headings (many fall between lanes or off them), at the
sensors' radius and a smaller one. The scan is plain numpy over all segments: the nearest
segment within the radius whose direction is within 90° of the heading (the lower segment of
equal distances), and the distance to the nearest segment of any direction.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from converters import iter_scenes
from magail_sumo.sensors import lanes as lane_module
from magail_sumo.sensors.lanes import LaneIndex
from magail_sumo.sensors.raycast import indexed_polyline_segments

DATA = Path(__file__).resolve().parents[1] / "data"
FILES = sorted((DATA / "scenarionet").glob("*.pkl")) + sorted((DATA / "womd").glob("*.tfrecord"))


def scan(lanes, x, y, yaw, radius):
    """(lane, lateral, heading error, distance) of each point by a scan of every segment."""
    a, b, owner = indexed_polyline_segments([ln.polyline for ln in lanes])
    ex, ey = (b - a)[:, 0], (b - a)[:, 1]
    ll = ex * ex + ey * ey
    wx, wy = x[:, None] - a[None, :, 0], y[:, None] - a[None, :, 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(ll < 1e-12, 0.0, np.clip((wx * ex + wy * ey) / ll, 0.0, 1.0))
    d2 = (wx - t * ex) ** 2 + (wy - t * ey) ** 2
    dist = np.sqrt(np.minimum(d2.min(1), radius * radius))
    ok = (ll >= 1e-12) & (d2 < radius * radius) & \
        (ex * np.cos(yaw)[:, None] + ey * np.sin(yaw)[:, None] > 0)
    masked = np.where(ok, d2, np.inf)
    best = masked.min(1)
    # the lowest segment among those at the nearest distance (ties at a shared vertex)
    k = np.argmax(ok & (masked <= best[:, None] + 1e-9), axis=1)
    found = np.isfinite(best)
    rows = np.arange(len(x))
    n = np.sqrt(ll[k])
    lane = np.where(found, owner[k], -1)
    lat = np.where(found, (ex[k] * wy[rows, k] - ey[k] * wx[rows, k]) / n, 0.0)
    herr = np.where(found, (yaw - np.arctan2(ey[k], ex[k]) + np.pi) % (2 * np.pi) - np.pi, 0.0)
    return lane, lat, herr, dist


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.stem)
def test_lane_index_equals_a_scan_of_every_segment(path):
    scene = next(iter(iter_scenes(path)))
    lanes = scene.roadmap.lanes
    assert lanes
    tr = scene.tracks
    rng = np.random.default_rng(0)
    x, y, h = (getattr(tr, n)[tr.valid].astype(np.float64) for n in ("x", "y", "heading"))
    keep = rng.permutation(len(x))[:400]
    x, y, h = x[keep], y[keep], h[keep]
    x = np.r_[x, x + rng.normal(0, 3, len(x))]
    y = np.r_[y, y + rng.normal(0, 3, len(y))]
    h = np.r_[h, rng.uniform(-np.pi, np.pi, len(h))]
    for radius in (10.0, 4.0):
        got = LaneIndex.build(lanes, cell=radius).query(x, y, h)
        lane, lat, herr, dist = scan(lanes, x, y, h, radius)
        assert (got.lane >= 0).any() and (got.lane < 0).any()
        np.testing.assert_array_equal(got.lane, lane)
        np.testing.assert_allclose(got.distance, dist, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.lateral, lat, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.heading_error, herr, rtol=0, atol=1e-9)


def test_grid_size_does_not_change_an_answer(monkeypatch):
    """Cells of a third, half and the whole radius: the same answers, bit for bit."""
    scene = next(iter(iter_scenes(FILES[0])))
    tr = scene.tracks
    x, y, h = (getattr(tr, n)[tr.valid].astype(np.float64) for n in ("x", "y", "heading"))
    answers = []
    for split in (1, 2, 3):
        monkeypatch.setattr(lane_module, "GRID_SPLIT", split)
        q = LaneIndex.build(scene.roadmap.lanes).query(x, y, h)
        answers.append((q.lane, q.lateral, q.heading_error, q.distance))
    for other in answers[1:]:
        for a, b in zip(answers[0], other):
            np.testing.assert_array_equal(a, b)
