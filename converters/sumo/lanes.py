"""The lanes of a built SUMO network as segments, and the test of a pose lying on them (the
quality figures' and the route matcher's shared geometry; definitions in :mod:`.quality`).

A pose is on a lane when it lies within half the lane's width + :data:`MARGIN` of one of its
segments and its heading is within :data:`MAX_ANGLE` of the segment's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

from .geometry import angle_diff, point_segment
from .pedestrians import is_walking_lane

MARGIN = 0.5  #: m beyond half the lane width
MAX_ANGLE = np.radians(45.0)


@dataclass(frozen=True)
class LaneSegments:
    """All lane segments of a built network: ends (S, 2), half width + margin (S,), heading, edge."""

    a: np.ndarray
    b: np.ndarray
    tol: np.ndarray
    heading: np.ndarray
    edge: np.ndarray  # (S,) edge id (internal edges start with ':')

    @classmethod
    def from_shapes(cls, lanes: Iterable[tuple[np.ndarray, float, str]]) -> "LaneSegments":
        """Segments of lanes given as (shape (P, >=2), width m, edge id); shorter shapes skipped."""
        a, b, tol, edge = [], [], [], []
        for shape, width, eid in lanes:
            if len(shape) < 2:
                continue
            a.append(shape[:-1, :2])
            b.append(shape[1:, :2])
            tol.append(np.full(len(shape) - 1, width / 2 + MARGIN))
            edge.append(np.full(len(shape) - 1, eid, dtype=object))
        a_, b_ = np.concatenate(a), np.concatenate(b)
        d = b_ - a_
        return cls(a_, b_, np.concatenate(tol), np.arctan2(d[:, 1], d[:, 0]), np.concatenate(edge))


def lane_segments(net) -> LaneSegments:
    """Segments of every lane (internal lanes included) of a sumolib net but the pedestrians'
    (sidewalks, crossings, walking areas: :func:`.pedestrians.is_walking_lane`)."""
    return LaneSegments.from_shapes(
        (np.asarray(lane.getShape(), dtype=np.float64), lane.getWidth(), e.getID())
        for e in net.getEdges(withInternal=True) for lane in e.getLanes()
        if not is_walking_lane(lane))


def on_lanes(seg: LaneSegments, xy: np.ndarray, heading: np.ndarray,
             mask: np.ndarray | None = None) -> np.ndarray:
    """(M,) bool: point within tolerance of a segment (of ``mask``) heading within 45°."""
    a, b, tol, hd = seg.a, seg.b, seg.tol, seg.heading
    if mask is not None:
        a, b, tol, hd = a[mask], b[mask], tol[mask], hd[mask]
    out = np.zeros(len(xy), bool)
    if not len(a):
        return out
    order = np.lexsort((xy[:, 1], xy[:, 0]))  # spatially coherent chunks for the bbox filter
    slo, shi = np.minimum(a, b) - tol[:, None], np.maximum(a, b) + tol[:, None]
    for lo in range(0, len(xy), 128):
        rows = order[lo:lo + 128]
        p, h = xy[rows], heading[rows]
        near = np.flatnonzero(np.all((slo <= p.max(axis=0)) & (shi >= p.min(axis=0)), axis=1))
        if not len(near):
            continue
        d, _ = point_segment(p, a[near], b[near])
        ok = (d <= tol[near][None]) & (angle_diff(h[:, None], hd[near][None]) <= MAX_ANGLE)
        out[rows] = ok.any(axis=1)
    return out
