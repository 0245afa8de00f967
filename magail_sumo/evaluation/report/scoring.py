"""Scores of an evaluation folder: traffic metrics and WOSAC realism per (scene, method).

Reads ``DIR/manifest.json`` and ``DIR/rollouts/<method>/<scenario_id>.parquet`` (written by
``magail-sumo evaluate``), optionally plus external submissions. Every rollout set is checked
against its scene (agent set, 80 steps, finite values); a bad one gives a one-line error naming
the scene / agent and the others are still scored.

Per (scene, method) the realism features are computed once and give both the scene's fields
and the per-agent rows (:func:`agent_metrics`); the states a method marks invalid (``valid``
column; log replay where the log has none) are kept as a mask so figures never draw them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from magail_sumo.errors import MagailSumoError
from magail_sumo.evaluation.realism.config import CHALLENGE_2025, Bernoulli, Histogram
from magail_sumo.evaluation.realism.estimators import (
    bernoulli_log_likelihood, histogram_log_likelihood,
)
from magail_sumo.evaluation.realism.metrics import (
    _FLAGS, _MASKS, Features, compute_features, metrics_from_features,
)
from magail_sumo.evaluation.realism.trajectories import joint_trajectories
from magail_sumo.evaluation.realism import kinematic
from magail_sumo.evaluation.rollouts import N_STEPS, read_manifest, read_rollouts, rollouts_path
from magail_sumo.evaluation.submission import (
    ScenarioRollouts, SubmissionError, iter_submission, validate_rollouts,
)
from magail_sumo.evaluation.traffic import MetricInput, compute_metrics
from magail_sumo.outputs import OutputError, printable
from magail_sumo.scene import ObjectType, Scene


@dataclass
class Scores:
    """Everything a report shows.

    :param rows: one dict per (scenario_id, method): traffic metrics and realism fields.
    :param inputs: the metric inputs (features) per (scenario_id, method), for figures.
    :param rollouts: the rollouts per (scenario_id, method).
    :param errors: one-line problems (scene / method / agent named).
    :param agent_rows: one dict per (scenario_id, method, evaluated agent): see
        :func:`agent_metrics`.
    :param valid: per (scenario_id, method), (R, A, T) bool: the states the method marked
        valid (absent: all valid).
    """

    manifest: dict
    scenes: dict[str, Scene]
    methods: list[str]
    rows: list[dict] = field(default_factory=list)
    inputs: dict[tuple[str, str], MetricInput] = field(default_factory=dict)
    rollouts: dict[tuple[str, str], ScenarioRollouts] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    agent_rows: list[dict] = field(default_factory=list)
    valid: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)


#: Per-agent columns of :func:`agent_metrics` (after scenario_id, method, object_id, type).
AGENT_FIELDS = [f"{fc.name}_likelihood" for fc in CHALLENGE_2025.features] + [
    "ade", "min_ade", "collision_rate", "offroad_rate"]


def agent_metrics(feat: Features, config=CHALLENGE_2025) -> dict[str, np.ndarray]:
    """Per evaluated agent (E,): each realism feature's likelihood (histogram features: exp of
    the mean log-likelihood over that agent's masked steps, NaN where it has none; Bernoulli
    features: the likelihood of its logged flag), ADE and minADE over rollouts (m), and the
    share of rollouts in which it collides / goes off-road — the per-agent parts of
    :func:`~magail_sumo.evaluation.realism.metrics.metrics_from_features`."""
    valid = feat.valid
    speed_mask = kinematic.central_valid(valid)
    masks = {"valid": valid, "speed": speed_mask, "accel": kinematic.central_valid(speed_mask),
             "vehicle": valid & feat.is_vehicle[:, None]}
    flag_mask = {"collision_indication": valid, "offroad_indication": valid,
                 "traffic_light_violation": valid & feat.is_vehicle[:, None]}
    out: dict[str, np.ndarray] = {}
    flags = {}
    with np.errstate(invalid="ignore", divide="ignore"):
        for fc in config.features:
            if isinstance(fc.estimator, Histogram):
                vals = feat.values[fc.name]
                ll = histogram_log_likelihood(vals[0], vals[1:], fc.estimator)
                m = masks[_MASKS[fc.name]]
                out[f"{fc.name}_likelihood"] = np.exp(np.where(m, ll, 0.0).sum(1) / m.sum(1))
            else:
                assert isinstance(fc.estimator, Bernoulli)
                f = (feat.values[_FLAGS[fc.name]] & flag_mask[fc.name]).any(-1)
                flags[fc.name] = f
                out[f"{fc.name}_likelihood"] = np.exp(
                    bernoulli_log_likelihood(f[0], f[1:], fc.estimator))
        lv = feat.log_valid_all
        ade = np.where(lv[None], feat.displacement, 0).sum(-1) / lv.sum(-1)  # (R, E)
    out["ade"] = ade.mean(0)
    out["min_ade"] = ade.min(0)
    out["collision_rate"] = flags["collision_indication"][1:].mean(0)
    out["offroad_rate"] = flags["offroad_indication"][1:].mean(0)
    return out


def read_valid(path: Path, scene: Scene, ro: ScenarioRollouts) -> np.ndarray | None:
    """(R, A, T) ``valid`` column of a rollouts file over the simulated steps, in
    :func:`~magail_sumo.evaluation.rollouts.read_rollouts`' order; None when all are valid."""
    import pandas as pd

    try:
        df = pd.read_parquet(path, columns=["rollout", "object_id", "step", "valid"])
        fut = df[df["step"] > scene.current_time_index]
        if bool(fut["valid"].all()):
            return None
        fut = fut.sort_values(["rollout", "object_id", "step"])
        return fut["valid"].to_numpy(bool).reshape(ro.shape)
    except Exception:  # noqa: BLE001 - read_rollouts accepted the file: draw every state
        return None


def load_scenes(manifest: dict, errors: list[str]) -> dict[str, Scene]:
    """The manifest's scenes, read from their files (missing ones reported)."""
    from converters import iter_scenes

    want = {s["scenario_id"]: s["file"] for s in manifest.get("scenes", [])}
    got: dict[str, Scene] = {}
    for f in dict.fromkeys(want.values()):
        try:
            for sc in iter_scenes(f):
                if sc.scenario_id in want:
                    got[sc.scenario_id] = sc
        except (MagailSumoError, OSError) as exc:
            errors.append(" ".join(str(exc).split()))
    for sid in want.keys() - got.keys():
        errors.append(f"scenario {printable(sid)}: not found in {want[sid]}")
    return got


def score(scores: Scores, sid: str, method: str, ro: ScenarioRollouts,
          valid: np.ndarray | None = None) -> None:
    """Validate and score one rollout set (errors are recorded, not raised)."""
    scene = scores.scenes[sid]
    try:
        validate_rollouts(ro, scene, ro.shape[0], N_STEPS)
        feat = compute_features(scene, joint_trajectories(scene, ro), CHALLENGE_2025)
        realism = metrics_from_features(feat, CHALLENGE_2025)
        per_agent = agent_metrics(feat)
        inp = MetricInput.build(scene, ro)
        traffic = compute_metrics(inp)
    except SubmissionError as exc:
        scores.errors.append(f"method {method}: {exc}")
        return
    except ValueError as exc:
        scores.errors.append(f"method {method}: scenario {sid}: {exc}")
        return
    scores.rows.append({"scenario_id": sid, "method": method, "rollouts": ro.shape[0],
                        **traffic, **realism})
    scores.inputs[(sid, method)] = inp
    scores.rollouts[(sid, method)] = ro
    if valid is not None:
        scores.valid[(sid, method)] = valid
    tr = scene.tracks
    for k, oid in enumerate(feat.object_id):
        row = int(np.flatnonzero(tr.id == oid)[0])
        scores.agent_rows.append({
            "scenario_id": sid, "method": method, "object_id": int(oid),
            "type": ObjectType(int(tr.type[row])).name.lower(),
            "sdc": row == scene.sdc_track_index,
            **{f: float(per_agent[f][k]) for f in AGENT_FIELDS}})
    if method not in scores.methods:
        scores.methods.append(method)


def collect(folder: str | Path, submissions: dict[str, list[str]] | None = None) -> Scores:
    """Score every method and scene of an evaluation folder, plus named external submissions
    (``{method name: [submission files]}``; a scenario not among the folder's scenes is an
    error)."""
    folder = Path(folder)
    manifest = read_manifest(folder)
    errors: list[str] = []
    scenes = load_scenes(manifest, errors)
    scores = Scores(manifest, scenes, [], errors=errors)
    for method in manifest.get("methods", []):
        for sid in scenes:
            try:
                path = rollouts_path(folder, method, sid)
            except OutputError as exc:
                scores.errors.append(f"method {printable(method)}: {exc}")
                continue
            if not path.is_file():
                scores.errors.append(f"method {printable(method)}: scenario {printable(sid)}: "
                                     f"no rollouts ({path})")
                continue
            try:
                ro = read_rollouts(path, scenes[sid])
                valid = read_valid(path, scenes[sid], ro)
            except MagailSumoError as exc:
                scores.errors.append(f"method {method}: {' '.join(str(exc).split())}")
                continue
            score(scores, sid, method, ro, valid)
    for method, files in (submissions or {}).items():
        try:
            for rec in iter_submission(files):
                if rec.error is not None:
                    scores.errors.append(f"method {method}: {rec.error}")
                elif rec.scenario_id not in scenes:
                    scores.errors.append(f"method {method}: scenario {rec.scenario_id}: not "
                                         "among the evaluated scenes")
                else:
                    score(scores, rec.scenario_id, method, rec.rollouts)  # type: ignore[arg-type]
        except SubmissionError as exc:
            scores.errors.append(f"method {method}: {exc}")
    return scores


def method_means(scores: Scores, fields: list[str]) -> dict[str, dict[str, float]]:
    """Per method, the mean over its scored scenes of each field (NaN-aware)."""
    out = {}
    for m in scores.methods:
        rows = [r for r in scores.rows if r["method"] == m]
        out[m] = {f: float(np.nanmean([r[f] for r in rows])) if any(
            np.isfinite(r[f]) for r in rows) else float("nan") for f in fields}
    return out
