"""WOSAC 2025 sim-agents realism metrics, in numpy (no TensorFlow).

``scenario_metrics(scene, rollouts)`` gives the official per-scenario fields; the modules hold
one concept each: ``config`` (the 2025 configuration as data), ``trajectories`` (agents and the
joint 91-step arrays), ``kinematic``, ``interaction``, ``road_edge`` (:mod:`magail_sumo.sensors.road_edge`), ``traffic_light``
(features), ``estimators`` (likelihoods) and ``metrics`` (aggregation).
"""

from magail_sumo.evaluation.realism.config import CHALLENGE_2025, ChallengeConfig
from magail_sumo.evaluation.realism.metrics import (
    FEATURE_NAMES, METRIC_FIELDS, Features, aggregate_metrics, bucket_metrics, compute_features,
    metrics_from_features, scenario_metrics,
)
from magail_sumo.evaluation.realism.trajectories import (
    evaluated_ids, joint_trajectories, log_replay,
)

__all__ = ["CHALLENGE_2025", "ChallengeConfig", "FEATURE_NAMES", "METRIC_FIELDS", "Features",
           "aggregate_metrics", "bucket_metrics", "compute_features", "evaluated_ids",
           "joint_trajectories", "log_replay", "metrics_from_features", "scenario_metrics"]
