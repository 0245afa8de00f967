"""The WOSAC 2025 sim-agents realism configuration, as data.

Each feature is scored by a likelihood estimator (a histogram over the rollouts' values, or a
Bernoulli over a per-object boolean) and weighted into the meta-metric. Values follow the
official 2025 challenge configuration.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Histogram:
    """Histogram estimator over ``[min_val, max_val]`` with ``num_bins`` equal bins.

    Values outside the range are clipped into the end bins; ``pseudocount`` is added to every
    bin count before normalising.
    """

    min_val: float
    max_val: float
    num_bins: int
    pseudocount: float = 0.1

    @property
    def edges(self) -> np.ndarray:
        """(num_bins + 1,) float32 bin edges, ``min + i * step`` in float32 arithmetic.

        This is bit-exact with the official (float32) linspace; numpy's own linspace differs
        by an ulp on some edges.
        """
        lo, hi = np.float32(self.min_val), np.float32(self.max_val)
        step = (hi - lo) / np.float32(self.num_bins)
        inner = lo + np.arange(self.num_bins, dtype=np.float32) * step
        return np.append(inner, hi).astype(np.float32)


@dataclass(frozen=True)
class Bernoulli:
    """Bernoulli estimator over a per-object boolean, with additive smoothing."""

    pseudocount: float = 0.001


@dataclass(frozen=True)
class FeatureConfig:
    """One scored feature: its official name, estimator and meta-metric weight."""

    name: str
    estimator: Histogram | Bernoulli
    weight: float


@dataclass(frozen=True)
class ChallengeConfig:
    """Protocol constants and the scored features.

    :param current_time_index: last history step (0-based); simulation starts after it.
    :param n_simulation_steps: simulated steps per rollout.
    :param n_rollouts: rollouts per scenario.
    :param step_duration_s: seconds per step.
    """

    current_time_index: int = 10
    n_simulation_steps: int = 80
    n_rollouts: int = 32
    step_duration_s: float = 0.1
    features: tuple[FeatureConfig, ...] = field(default_factory=tuple)

    @property
    def n_steps(self) -> int:
        """History plus simulated steps (91)."""
        return self.current_time_index + 1 + self.n_simulation_steps

    def feature(self, name: str) -> FeatureConfig:
        for f in self.features:
            if f.name == name:
                return f
        raise KeyError(name)


CHALLENGE_2025 = ChallengeConfig(features=(
    FeatureConfig("linear_speed", Histogram(0.0, 25.0, 10), 0.05),
    FeatureConfig("linear_acceleration", Histogram(-12.0, 12.0, 11), 0.05),
    FeatureConfig("angular_speed", Histogram(-0.628, 0.628, 11), 0.05),
    FeatureConfig("angular_acceleration", Histogram(-3.14, 3.14, 11), 0.05),
    FeatureConfig("distance_to_nearest_object", Histogram(-5.0, 40.0, 10), 0.10),
    FeatureConfig("collision_indication", Bernoulli(), 0.25),
    FeatureConfig("time_to_collision", Histogram(0.0, 5.0, 10), 0.10),
    FeatureConfig("distance_to_road_edge", Histogram(-20.0, 40.0, 10), 0.05),
    FeatureConfig("offroad_indication", Bernoulli(), 0.25),
    FeatureConfig("traffic_light_violation", Bernoulli(), 0.05),
))

#: Meta-metric buckets: feature names per bucket.
BUCKETS = {
    "kinematic_metrics": ("linear_speed", "linear_acceleration", "angular_speed",
                          "angular_acceleration"),
    "interactive_metrics": ("distance_to_nearest_object", "collision_indication",
                            "time_to_collision"),
    "map_based_metrics": ("distance_to_road_edge", "offroad_indication",
                          "traffic_light_violation"),
}
