"""Event rates: share of (rollout, object) pairs with at least one event step on the log-valid
steps (collision: box overlap, off-road: a box corner beyond the road edge, both from the
realism features; off-road is NaN on a map without road edges; red-light violation; hard
braking: acceleration < -3 m/s²)."""

from __future__ import annotations

import math

import numpy as np

from .base import MetricInput, TrafficMetric, register

HARD_BRAKE = -3.0  #: m/s²


def _rate(flags: np.ndarray, mask: np.ndarray) -> float:
    """flags (B, A, T) on mask (A, T): share of the rollouts' objects with any event."""
    rows = mask.any(1)
    if not rows.any():
        return float("nan")
    return float((flags[1:] & mask[None]).any(2)[:, rows].mean())


@register
class CollisionRate(TrafficMetric):
    name, unit = "collision_rate", "share of objects"
    description = "objects colliding with another object at least once"

    def compute(self, inp: MetricInput) -> float:
        return _rate(inp.feature("collision_per_step"), inp.valid)


@register
class OffroadRate(TrafficMetric):
    name, unit = "offroad_rate", "share of vehicles"
    description = "vehicles with a box corner beyond the road edge at least once"

    def compute(self, inp: MetricInput) -> float:
        if "offroad_per_step" not in inp.feat.values:  # a map without road edges
            return float("nan")
        return _rate(inp.feature("offroad_per_step"), inp.valid & inp.is_vehicle[:, None])


def log_offroad(inp: MetricInput) -> tuple[float, int]:
    """:class:`OffroadRate` of the recording itself (the log's batch row) and its count: the
    share and the number of the scene's vehicles whose recorded box leaves the road edges at
    least once over the simulated steps; (NaN, 0) on a map without road edges or without
    vehicles. A scene property, the same for every method: where it is high the map's road
    edges disagree with the log, and off-road figures on that scene say little
    (:data:`ROAD_EDGES_DISAGREE`)."""
    if "offroad_per_step" not in inp.feat.values:
        return float("nan"), 0
    mask = inp.valid & inp.is_vehicle[:, None]
    rows = mask.any(1)
    if not rows.any():
        return float("nan"), 0
    off = (inp.feature("offroad_per_step")[0] & mask).any(1)[rows]
    return float(off.mean()), int(off.sum())


#: a scene's road edges are taken to disagree with its log when the recording puts more than
#: this share of its vehicles off them, and at least :data:`ROAD_EDGES_DISAGREE_VEHICLES`
#: vehicles (the MetaVQA maps: see ``../shared/data/README.md``); the report gives off-road
#: rates on such scenes apart
ROAD_EDGES_DISAGREE = 0.2
ROAD_EDGES_DISAGREE_VEHICLES = 3


def road_edges_disagree_with_log(share: float, count: float) -> bool:
    """Whether a scene's road edges disagree with its log, from :func:`log_offroad`'s share and
    count of the recorded vehicles off them (NaN share: no road edges, no verdict: False)."""
    return math.isfinite(share) and share > ROAD_EDGES_DISAGREE \
        and count >= ROAD_EDGES_DISAGREE_VEHICLES


@register
class RedLightRate(TrafficMetric):
    name, unit = "red_light_rate", "share of vehicles"
    description = "vehicles crossing a stop line on red at least once"

    def compute(self, inp: MetricInput) -> float:
        return _rate(inp.feature("traffic_light_violation_per_step"),
                     inp.valid & inp.is_vehicle[:, None])


@register
class HardBrakingRate(TrafficMetric):
    name, unit = "hard_braking_rate", "share of vehicles"
    description = "vehicles braking harder than 3 m/s² at least once"

    def compute(self, inp: MetricInput) -> float:
        acc = inp.feature("linear_acceleration")
        with np.errstate(invalid="ignore"):
            flags = np.nan_to_num(acc, nan=0.0) < HARD_BRAKE
        return _rate(flags, inp.mask("linear_acceleration") & inp.is_vehicle[:, None])
