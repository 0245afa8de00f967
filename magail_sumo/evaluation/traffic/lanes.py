"""Lane changes: per vehicle and rollout, the number of times its nearest lane (centre line
within 90° of its heading, :class:`~magail_sumo.sensors.lanes.LaneIndex`) switches to a left or
right neighbour of the previous lane (successor/predecessor switches are not lane changes)."""

from __future__ import annotations

import dataclasses

import numpy as np

from magail_sumo.evaluation.realism.metrics import distinct_rows
from magail_sumo.sensors.lanes import LaneIndex

from .base import MetricInput, TrafficMetric, register

MAX_LATERAL = 3.0  #: m from the centre line beyond which a match is ignored


def lane_sequence(inp: MetricInput) -> np.ndarray:
    """(B, A, T) lane index into ``scene.roadmap.lanes`` of each pose at the log-valid steps
    (the only ones a lane change counts at); -1: none, or a step the log has no state at.

    Poses are looked up once per distinct batch row (log replay and constant-velocity
    rollouts repeat one row)."""
    lanes = inp.scene.roadmap.lanes
    index = LaneIndex.build(lanes)
    first, inverse = distinct_rows(inp.x, inp.y, inp.heading)
    x, y, h = inp.x[first], inp.y[first], inp.heading[first]
    at = np.broadcast_to(inp.valid[None], x.shape)
    q = index.query(x[at], y[at], h[at])
    lane = np.full(x.shape, -1, np.int64)
    lane[at] = np.where(np.abs(q.lateral) <= MAX_LATERAL, q.lane, -1)
    return lane[inverse]


def neighbour_pairs(inp: MetricInput) -> np.ndarray:
    """Sorted codes ``i * L + j`` of lane-index pairs (i, j) where j neighbours i."""
    lanes = inp.scene.roadmap.lanes
    pos = {ln.id: k for k, ln in enumerate(lanes)}
    n = len(lanes)
    codes = [i * n + pos[nb.feature_id] for i, ln in enumerate(lanes)
             for nb in (*ln.left_neighbors, *ln.right_neighbors) if nb.feature_id in pos]
    return np.unique(np.asarray(codes, np.int64))


def lane_changes(inp: MetricInput) -> np.ndarray:
    """(B, A) lane changes of each object over the log-valid simulated steps."""
    seq = lane_sequence(inp)
    n = len(inp.scene.roadmap.lanes)
    # carry the last matched lane over unmatched steps
    t = np.arange(seq.shape[2])
    ok = (seq >= 0) & inp.valid[None]
    last = np.maximum.accumulate(np.where(ok, t, -1), axis=2)
    held = np.where(last >= 0, np.take_along_axis(seq, np.maximum(last, 0), 2), -1)
    a, b = held[..., :-1], held[..., 1:]
    step = (a >= 0) & (b >= 0) & (a != b) & ok[..., 1:]
    code = a.astype(np.int64) * n + b
    return (step & np.isin(code, neighbour_pairs(inp))).sum(2)


@register
class LaneChanges(TrafficMetric):
    name, unit = "lane_changes", "per vehicle per 8 s"
    description = "lane changes (switches to a neighbouring lane) per vehicle"

    def compute(self, inp: MetricInput) -> float:
        rows = inp.is_vehicle & inp.valid.any(1)
        if not rows.any():
            return float("nan")
        # only the rollouts' vehicles count: look up nothing else (an object's count depends
        # on its own poses only)
        sub = dataclasses.replace(inp, x=inp.x[1:, rows], y=inp.y[1:, rows],
                                  heading=inp.heading[1:, rows], valid=inp.valid[rows],
                                  is_vehicle=inp.is_vehicle[rows])
        return float(lane_changes(sub).mean())
