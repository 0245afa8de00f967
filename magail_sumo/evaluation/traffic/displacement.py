"""Displacement from the log: ADE, minADE, FDE (metres, 2-D, over the log-valid future steps)."""

from __future__ import annotations

import numpy as np

from .base import MetricInput, TrafficMetric, register


def displacement(inp: MetricInput) -> np.ndarray:
    """(R, A, T) 2-D distance (m) of each rollout to the log."""
    return np.hypot(inp.x[1:] - inp.x[:1], inp.y[1:] - inp.y[:1])


def _per_rollout_ade(inp: MetricInput) -> np.ndarray:
    d = displacement(inp)
    n = inp.valid.sum(1)
    has = n > 0
    ade = np.where(inp.valid[None], d, 0).sum(2)[:, has] / n[has]  # (R, A')
    return ade.mean(1) if ade.size else np.full(d.shape[0], np.nan)


@register
class ADE(TrafficMetric):
    name, unit = "ade", "m"
    description = "mean over rollouts and objects of the mean displacement from the log"

    def compute(self, inp: MetricInput) -> float:
        return float(_per_rollout_ade(inp).mean())


@register
class MinADE(TrafficMetric):
    name, unit = "min_ade", "m"
    description = "best rollout's ADE"

    def compute(self, inp: MetricInput) -> float:
        return float(_per_rollout_ade(inp).min())


@register
class FDE(TrafficMetric):
    name, unit = "fde", "m"
    description = "mean displacement at each object's last log-valid simulated step"

    def compute(self, inp: MetricInput) -> float:
        v = inp.valid
        has = v.any(1)
        if not has.any():
            return float("nan")
        last = v.shape[1] - 1 - np.argmax(v[:, ::-1], axis=1)
        d = displacement(inp)[:, np.flatnonzero(has), last[has]]
        return float(d.mean())
