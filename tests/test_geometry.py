"""Polyline geometry of the converter (converters/sumo/geometry.py)."""

from __future__ import annotations

import numpy as np

from converters.sumo.geometry import point_segment


def test_point_segment_matches_the_stacked_form_bit_for_bit():
    """The component-wise distance kernel (the map matcher's hot path) gives exactly what the
    (M, S, 2) form gives, zero-length segments included, in log coordinates km from 0."""
    rng = np.random.default_rng(0)
    for m, s in ((1, 1), (5, 7), (91, 2000)):
        p = rng.normal(size=(m, 2)) * 80 + 5000
        a = rng.normal(size=(s, 2)) * 80 + 5000
        b = a + rng.normal(size=(s, 2)) * 3
        b[::4] = a[::4]
        d = b - a
        t_ref = np.clip(((p[:, None] - a[None]) * d[None]).sum(2)
                        / np.maximum((d * d).sum(1), 1e-12)[None], 0.0, 1.0)
        d_ref = np.linalg.norm(p[:, None] - (a[None] + t_ref[..., None] * d[None]), axis=2)
        dist, t = point_segment(p, a, b)
        assert np.array_equal(dist, d_ref) and np.array_equal(t, t_ref)
    # a point on a segment, beyond its end, and a zero-length segment
    dist, t = point_segment(np.array([[1.0, 0.0], [3.0, 0.0]]), np.array([[0.0, 0.0], [5.0, 5.0]]),
                            np.array([[2.0, 0.0], [5.0, 5.0]]))
    assert np.allclose(dist[:, 0], [0.0, 1.0]) and np.allclose(t[:, 0], [0.5, 1.0])
    assert np.isclose(dist[0, 1], np.hypot(4.0, 5.0))
