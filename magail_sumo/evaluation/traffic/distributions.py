"""Distribution metrics: Jensen–Shannon divergence (base 2, in [0, 1]) between the rollouts'
and the log's histograms of a per-step feature on common bins, plus plain means.

Bins (values outside are clipped into the end bins): speed 0..30 m/s, acceleration ±10 m/s²,
jerk ±50 m/s³, yaw rate ±1.5 rad/s, distance to the nearest object 0..40 m, TTC 0..5 s.
"""

from __future__ import annotations

import numpy as np

from .base import MetricInput, TrafficMetric, register

#: feature -> (lo, hi, bins)
BINS: dict[str, tuple[float, float, int]] = {
    "linear_speed": (0.0, 30.0, 30),
    "linear_acceleration": (-10.0, 10.0, 40),
    "jerk": (-50.0, 50.0, 40),
    "angular_speed": (-1.5, 1.5, 30),
    "distance_to_nearest_object": (0.0, 40.0, 40),
    "time_to_collision": (0.0, 5.0, 25),
}


def counts(values: np.ndarray, feature: str) -> np.ndarray:
    """(bins,) int64 counts of ``values`` on the feature's bins (end bins take the outliers)."""
    lo, hi, n = BINS[feature]
    edges = np.linspace(lo, hi, n + 1)
    idx = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, n - 1)
    return np.bincount(idx, minlength=n).astype(np.int64)


def histogram(values: np.ndarray, feature: str) -> np.ndarray:
    """Normalised histogram of ``values`` on the feature's bins (end bins take the outliers)."""
    h = counts(values, feature).astype(np.float64)
    return h / max(h.sum(), 1.0)


def js_divergence(p: np.ndarray, q: np.ndarray) -> float:
    """Jensen–Shannon divergence (bits) of two normalised histograms."""
    m = (p + q) / 2

    def kl(a: np.ndarray) -> float:
        nz = a > 0
        return float((a[nz] * np.log2(a[nz] / m[nz])).sum())

    return 0.5 * kl(p) + 0.5 * kl(q)


def feature_js(inp: MetricInput, feature: str) -> float:
    log, sim = inp.log_and_sim(feature)
    if not log.size or not sim.size:
        return float("nan")
    return js_divergence(histogram(sim, feature), histogram(log, feature))


def _js_metric(feature: str, label: str) -> type[TrafficMetric]:
    class _JS(TrafficMetric):
        name, unit = f"{label}_js", "bits"
        description = f"Jensen-Shannon divergence of the {label} distribution from the log's"

        def compute(self, inp: MetricInput) -> float:
            return feature_js(inp, feature)

    _JS.__name__ = _JS.__qualname__ = f"{label.title().replace('_', '')}JS"
    return register(_JS)


SpeedJS = _js_metric("linear_speed", "speed")
AccelerationJS = _js_metric("linear_acceleration", "acceleration")
JerkJS = _js_metric("jerk", "jerk")
YawRateJS = _js_metric("angular_speed", "yaw_rate")
NearestObjectJS = _js_metric("distance_to_nearest_object", "nearest_object_distance")
TTCJS = _js_metric("time_to_collision", "ttc")


@register
class MeanSpeed(TrafficMetric):
    name, unit, lower_is_better = "mean_speed", "m/s", False
    description = "mean speed over object-steps"

    def compute(self, inp: MetricInput) -> float:
        _, sim = inp.log_and_sim("linear_speed")
        return float(sim.mean()) if sim.size else float("nan")


@register
class SpeedBias(TrafficMetric):
    """Mean simulated minus mean logged speed over the same object-steps (m/s):

    ``b = mean_{r,(a,t) in S} v^sim_{r,a,t} - mean_{r,(a,t) in S} v^log_{a,t}``, where ``S`` is
    the set of object-steps where the log defines the speed (:meth:`MetricInput.mask` of
    ``linear_speed``: log-valid with valid neighbours) and both speeds are finite, and
    ``r`` runs over the rollouts. Negative: the method drives slower than the recorded road
    users; 0 is best (so it is neither a higher- nor a lower-is-better figure)."""

    name, unit, lower_is_better = "speed_bias", "m/s", False
    description = "mean simulated minus mean logged speed over the same object-steps"

    def compute(self, inp: MetricInput) -> float:
        v = inp.feature("linear_speed")
        m = inp.mask("linear_speed")
        log, sim = v[0][m], v[1:][:, m]  # (K,), (R, K)
        ok = np.isfinite(sim) & np.isfinite(log)[None]
        if not ok.any():
            return float("nan")
        return float(sim[ok].mean() - np.broadcast_to(log, sim.shape)[ok].mean())


@register
class NearestObjectDistance(TrafficMetric):
    name, unit, lower_is_better = "nearest_object_distance", "m", False
    description = "median distance to the nearest other object (box to box)"

    def compute(self, inp: MetricInput) -> float:
        _, sim = inp.log_and_sim("distance_to_nearest_object")
        sim = sim[sim < 1e9]
        return float(np.median(sim)) if sim.size else float("nan")


@register
class LowTTCShare(TrafficMetric):
    name, unit = "ttc_below_1s", "share of vehicle-steps"
    description = "vehicle-steps with time to collision under 1 s"

    def compute(self, inp: MetricInput) -> float:
        _, sim = inp.log_and_sim("time_to_collision")
        return float((sim < 1.0).mean()) if sim.size else float("nan")
