"""Traffic metrics of rollouts against the log (one class per metric, registry + factory) and
city-scale SUMO figures from SUMO's outputs.

``compute_metrics(MetricInput.build(scene, rollouts))`` gives every registered metric of one
scene; see each module for definitions and units.
"""

from magail_sumo.evaluation.traffic import displacement, distributions, events, lanes, route
from magail_sumo.evaluation.traffic.base import (
    METRICS, MetricInput, TrafficMetric, compute_metrics, make_metric, register,
)
from magail_sumo.evaluation.traffic.sumo_outputs import (
    SumoRunError, SumoRunSummary, compare_runs, run_sumo_outputs, summarise,
)

__all__ = ["METRICS", "MetricInput", "SumoRunError", "SumoRunSummary", "TrafficMetric",
           "compare_runs", "compute_metrics", "displacement", "distributions", "events",
           "lanes", "make_metric", "register", "route", "run_sumo_outputs", "summarise"]
