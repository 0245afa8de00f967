"""Route completion: how far along its recorded future path each object got.

For each object with a recorded future path of at least 5 m (the log-valid simulated steps),
completion = arc length of the recorded path point nearest to the object's final simulated
position / total recorded path length, in [0, 1]; 0 when that nearest point is more than 5 m
away (the object left its route).
"""

from __future__ import annotations

import numpy as np

from .base import MetricInput, TrafficMetric, register

MIN_PATH = 5.0  #: m
MAX_OFF_PATH = 5.0  #: m


def route_completion(inp: MetricInput) -> tuple[np.ndarray, np.ndarray]:
    """(R, A) completion per rollout and object, and (A,) bool: objects with a path."""
    v = inp.valid
    lx = np.where(v, inp.x[0], np.nan).astype(np.float64)
    ly = np.where(v, inp.y[0], np.nan).astype(np.float64)
    seg = np.hypot(np.diff(lx, axis=1), np.diff(ly, axis=1))
    arc = np.concatenate([np.zeros((len(v), 1)), np.nancumsum(seg, axis=1)], axis=1)  # (A, T)
    total = np.nanmax(np.where(v, arc, np.nan), axis=1, initial=0.0) if v.size else np.zeros(0)
    has = v.any(1) & (total >= MIN_PATH)
    last = v.shape[1] - 1 - np.argmax(v[:, ::-1], axis=1)
    a = np.arange(len(v))
    fx, fy = inp.x[1:, a, last], inp.y[1:, a, last]  # (R, A) at the last log-valid step
    d = np.hypot(fx[..., None] - lx[None], fy[..., None] - ly[None])  # (R, A, T)
    d = np.where(np.isfinite(d), d, np.inf)
    k = d.argmin(2)
    near = np.take_along_axis(d, k[..., None], 2)[..., 0]
    prog = np.take_along_axis(np.broadcast_to(arc, d.shape), k[..., None], 2)[..., 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        comp = np.where(near <= MAX_OFF_PATH, prog / np.where(total > 0, total, 1.0), 0.0)
    return np.clip(comp, 0.0, 1.0), has


@register
class RouteCompletion(TrafficMetric):
    name, unit, lower_is_better = "route_completion", "share of recorded path", False
    description = "progress along the recorded future path (objects moving >= 5 m)"

    def compute(self, inp: MetricInput) -> float:
        comp, has = route_completion(inp)
        return float(comp[:, has].mean()) if has.any() else float("nan")
