"""Scenario realism metrics: features of the log and the rollouts, per-feature likelihoods,
the weighted meta-metric, ADE / minADE and simulated event rates (official field names)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magail_sumo.evaluation.realism import interaction, kinematic, traffic_light
from magail_sumo.sensors import road_edge as map_features
from magail_sumo.evaluation.realism.config import (
    BUCKETS, CHALLENGE_2025, Bernoulli, ChallengeConfig, FeatureConfig, Histogram,
)
from magail_sumo.evaluation.realism.estimators import (
    bernoulli_log_likelihood, histogram_log_likelihood, masked_mean_likelihood,
)
from magail_sumo.evaluation.realism.trajectories import JointTrajectories, joint_trajectories
from magail_sumo.evaluation.submission import ScenarioRollouts, validate_rollouts
from magail_sumo.scene import ObjectType, Scene

#: Output fields in the official order (``SimAgentMetrics``).
METRIC_FIELDS = (
    "metametric", "average_displacement_error", "min_average_displacement_error",
    "linear_speed_likelihood", "linear_acceleration_likelihood", "angular_speed_likelihood",
    "angular_acceleration_likelihood", "distance_to_nearest_object_likelihood",
    "collision_indication_likelihood", "time_to_collision_likelihood",
    "distance_to_road_edge_likelihood", "offroad_indication_likelihood",
    "traffic_light_violation_likelihood", "simulated_collision_rate", "simulated_offroad_rate",
    "simulated_traffic_light_violation_rate",
)

#: Per-step features (official names) of a :class:`Features` bundle.
FEATURE_NAMES = (
    "linear_speed", "linear_acceleration", "angular_speed", "angular_acceleration",
    "distance_to_nearest_object", "collision_per_step", "time_to_collision",
    "distance_to_road_edge", "offroad_per_step", "traffic_light_violation_per_step",
)


#: Per-step features that need the map's road edges: absent from :attr:`Features.values` of a
#: scene without any (:func:`~magail_sumo.sensors.road_edge.has_road_edges`).
ROAD_EDGE_FEATURES = ("distance_to_road_edge", "offroad_per_step")


@dataclass(frozen=True, eq=False)
class Features:
    """Per-step features of the evaluated objects over the simulated steps.

    Each value of ``values`` is ``(B, E, T_sim)``: row 0 the log, rows 1.. the rollouts. A
    scene whose map has no road edges lacks :data:`ROAD_EDGE_FEATURES` (every other feature is
    computed as usual).

    :param object_id: (E,) ids of the evaluated objects (ascending).
    :param is_vehicle: (E,) bool.
    :param valid: (E, T_sim) bool, the log's validity over the simulated steps.
    :param displacement: (R, E, T_all) float32 3-D distance (m) of rollouts to the log over all
        steps (history included, where it is 0).
    :param log_valid_all: (E, T_all) bool, the log's validity over all steps.
    """

    object_id: np.ndarray
    is_vehicle: np.ndarray
    valid: np.ndarray
    values: dict[str, np.ndarray]
    displacement: np.ndarray
    log_valid_all: np.ndarray


def distinct_rows(*arrays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batch rows (axis 0) of the arrays that are byte-for-byte distinct: ``(first, inverse)``
    with ``first`` the index of each distinct row's first occurrence and ``inverse`` (B,) the
    distinct row of every batch row (log replay and constant-velocity rollouts repeat one row).
    """
    seen: dict[bytes, int] = {}
    first, inverse = [], []
    for k in range(arrays[0].shape[0]):
        key = b"".join(np.ascontiguousarray(a[k]).tobytes() for a in arrays)
        if key not in seen:
            seen[key] = len(first)
            first.append(k)
        inverse.append(seen[key])
    return np.asarray(first, np.int64), np.asarray(inverse, np.int64)


def _row_features(scene: Scene, jt: JointTrajectories, rows: np.ndarray,
                  config: ChallengeConfig) -> dict[str, np.ndarray]:
    """The per-step features of batch ``rows`` of ``jt`` (each row's features depend on that
    row only); a scene without road edges has no :data:`ROAD_EDGE_FEATURES`."""
    E = jt.n_eval
    fut = slice(scene.current_time_index + 1, None)  # the scene's own history length
    dt = config.step_duration_s
    x, y, z, h, v = (a[rows] for a in (jt.x, jt.y, jt.z, jt.heading, jt.valid))
    speed, accel, ang_speed, ang_accel = kinematic.kinematic_features(
        x[:, :E], y[:, :E], z[:, :E], h[:, :E], dt)
    # interaction features need only the simulated steps (plus the 2-D speed, central diffs)
    speed2d = kinematic.linear_speed(x, y, np.zeros_like(x), dt)[..., fut]
    xs, ys, hs, vs = x[..., fut], y[..., fut], h[..., fut], v[..., fut]
    ls, ws = jt.length[:, fut], jt.width[:, fut]
    dist_obj = interaction.distance_to_nearest_object(xs, ys, hs, ls, ws, vs, E)
    ttc = interaction.time_to_collision(xs, ys, hs, ls, ws, vs, speed2d, E)
    dist_edge = offroad = None
    if map_features.has_road_edges(scene):
        segs = map_features.road_edge_segments(scene)
        dist_edge = map_features.distance_to_road_edge(
            xs[:, :E], ys[:, :E], z[:, :E, fut], hs[:, :E], ls[:E], ws[:E],
            jt.height[:E, fut], vs[:, :E], segs)
        offroad = dist_edge > map_features.OFFROAD_DISTANCE_THRESHOLD
    lanes = traffic_light.signal_lanes(scene, x.shape[-1])
    tl = traffic_light.red_light_violation(x[:, :E], y[:, :E], v[:, :E], lanes)[..., fut]
    out = {
        "linear_speed": speed[..., fut], "linear_acceleration": accel[..., fut],
        "angular_speed": ang_speed[..., fut], "angular_acceleration": ang_accel[..., fut],
        "distance_to_nearest_object": dist_obj,
        "collision_per_step": dist_obj < interaction.COLLISION_DISTANCE_THRESHOLD,
        "time_to_collision": ttc, "distance_to_road_edge": dist_edge,
        "offroad_per_step": offroad,
        "traffic_light_violation_per_step": tl,
    }
    return {k: a for k, a in out.items() if a is not None}


def log_features(scene: Scene, jt: JointTrajectories,
                 config: ChallengeConfig = CHALLENGE_2025) -> dict[str, np.ndarray]:
    """The per-step features of the log alone (batch row 0 of ``jt``, values ``(1, E, T_sim)``):
    the same for every rollout set of the scene with the same agents and ``n_eval``, so a
    caller scoring several passes them to :func:`compute_features`."""
    return _row_features(scene, jt, np.zeros(1, np.int64), config)


def compute_features(scene: Scene, jt: JointTrajectories,
                     config: ChallengeConfig = CHALLENGE_2025,
                     log_values: dict[str, np.ndarray] | None = None) -> Features:
    """All per-step features of the log and rollouts of ``jt`` (vectorised over both).

    Features are computed once per distinct batch row (:func:`distinct_rows`) and repeated
    for the rows equal to it: the same values as computing every row.

    :param log_values: :func:`log_features` of the scene's log, computed before (for another
        rollout set of the scene): only the rollouts' rows are computed."""
    E = jt.n_eval
    fut = slice(scene.current_time_index + 1, None)
    x, y, z = jt.x, jt.y, jt.z
    first, inverse = distinct_rows(x, y, z, jt.heading, jt.valid)
    if log_values is None:
        values = _row_features(scene, jt, first, config)
    elif len(first) == 1:  # every rollout equals the log
        values = dict(log_values)
    else:  # row 0, the log, is always the first distinct row
        rest = _row_features(scene, jt, first[1:], config)
        values = {k: np.concatenate([log_values[k], rest[k]]) for k in rest}
    if len(first) < x.shape[0]:
        values = {k: v[inverse] for k, v in values.items()}
    disp = np.sqrt((x[1:, :E] - x[:1, :E]) ** 2 + (y[1:, :E] - y[:1, :E]) ** 2
                   + (z[1:, :E] - z[:1, :E]) ** 2)
    return Features(jt.object_id[:E], jt.object_type[:E] == int(ObjectType.VEHICLE),
                    jt.log_valid[:E, fut], values, disp, jt.log_valid[:E])


#: Histogram features and the mask each likelihood is averaged over.
_MASKS = {
    "linear_speed": "speed", "angular_speed": "speed",
    "linear_acceleration": "accel", "angular_acceleration": "accel",
    "distance_to_nearest_object": "valid", "distance_to_road_edge": "valid",
    "time_to_collision": "vehicle",
}
_FLAGS = {"collision_indication": "collision_per_step", "offroad_indication": "offroad_per_step",
          "traffic_light_violation": "traffic_light_violation_per_step"}


def feature_masks(feat: Features) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The (E, T) step masks of the realism features: histogram features by mask name
    (``valid``, ``speed``, ``accel``, ``vehicle``; see ``_MASKS``) and Bernoulli features by
    feature name (collision and off-road over valid steps, traffic lights over vehicles')."""
    valid = feat.valid
    speed_mask = kinematic.central_valid(valid)
    masks = {"valid": valid, "speed": speed_mask, "accel": kinematic.central_valid(speed_mask),
             "vehicle": valid & feat.is_vehicle[:, None]}
    flag_mask = {"collision_indication": valid, "offroad_indication": valid,
                 "traffic_light_violation": valid & feat.is_vehicle[:, None]}
    return masks, flag_mask


def value_name(fc: FeatureConfig) -> str:
    """The :attr:`Features.values` key a scored feature is computed from."""
    return _FLAGS.get(fc.name, fc.name) if isinstance(fc.estimator, Bernoulli) else fc.name


def metrics_from_features(feat: Features, config: ChallengeConfig = CHALLENGE_2025
                          ) -> dict[str, float]:
    """The official per-scenario fields from a feature bundle.

    Without road edges (:data:`ROAD_EDGE_FEATURES` absent) the road-edge likelihoods and
    ``simulated_offroad_rate`` are NaN, and so is ``metametric`` (its weighted sum needs every
    component: not comparable with scenes that have it); every other field is as usual."""
    valid = feat.valid
    masks, flag_mask = feature_masks(feat)
    out: dict[str, float] = {}
    flags = {}
    for fc in config.features:
        if value_name(fc) not in feat.values:  # a road-edge feature of a map without edges
            out[f"{fc.name}_likelihood"] = float("nan")
        elif isinstance(fc.estimator, Histogram):
            vals = feat.values[fc.name]
            ll = histogram_log_likelihood(vals[0], vals[1:], fc.estimator)
            out[f"{fc.name}_likelihood"] = masked_mean_likelihood(ll, masks[_MASKS[fc.name]])
        else:
            assert isinstance(fc.estimator, Bernoulli)
            per_step = feat.values[_FLAGS[fc.name]] & flag_mask[fc.name]
            f = per_step.any(-1)  # (B, E)
            flags[fc.name] = f
            ll = bernoulli_log_likelihood(f[0], f[1:], fc.estimator)
            out[f"{fc.name}_likelihood"] = float(np.exp(ll.mean()))
    out["metametric"] = float(sum(fc.weight * out[f"{fc.name}_likelihood"]
                                  for fc in config.features))
    lv = feat.log_valid_all
    ade = np.where(lv[None], feat.displacement, 0).sum(-1) / lv.sum(-1)  # (R, E)
    out["average_displacement_error"] = float(ade.mean())
    out["min_average_displacement_error"] = float(ade.mean(1).min())
    out["simulated_collision_rate"] = float(flags["collision_indication"][1:].mean())
    out["simulated_offroad_rate"] = float(flags["offroad_indication"][1:].mean()) \
        if "offroad_indication" in flags else float("nan")
    tl_any = (feat.values["traffic_light_violation_per_step"][1:] & valid).any(-1)
    out["simulated_traffic_light_violation_rate"] = float(tl_any.mean())
    return {k: out[k] for k in METRIC_FIELDS}


def scenario_metrics(scene: Scene, rollouts: ScenarioRollouts,
                     config: ChallengeConfig = CHALLENGE_2025,
                     validate: bool = True) -> dict[str, float]:
    """Realism metrics of one scenario's rollouts (official field names and definitions).

    A scene whose map has no road edges gets NaN road-edge fields and meta-metric (see
    :func:`metrics_from_features`).

    :raises SubmissionError: rollouts that do not fit the scene (when ``validate``).
    """
    if validate:
        validate_rollouts(rollouts, scene, config.n_rollouts, config.n_simulation_steps)
    feat = compute_features(scene, joint_trajectories(scene, rollouts), config)
    return metrics_from_features(feat, config)


def aggregate_metrics(per_scenario: list[dict[str, float]]) -> dict[str, float]:
    """Dataset-level fields: the plain mean over scenarios of each field."""
    return {k: float(np.mean([m[k] for m in per_scenario])) for k in METRIC_FIELDS}


def bucket_metrics(agg: dict[str, float], config: ChallengeConfig = CHALLENGE_2025
                   ) -> dict[str, float]:
    """Meta-metric buckets (weighted means of their features' likelihoods) of dataset fields."""
    out = {"realism_meta_metric": agg["metametric"]}
    for bucket, names in BUCKETS.items():
        w = [config.feature(n).weight for n in names]
        out[bucket] = float(sum(wi * agg[f"{n}_likelihood"] for wi, n in zip(w, names)) / sum(w))
    out["min_ade"] = agg["min_average_displacement_error"]
    for k in ("simulated_collision_rate", "simulated_offroad_rate",
              "simulated_traffic_light_violation_rate"):
        out[k] = agg[k]
    return out
