"""Scores of an evaluation folder: traffic metrics and WOSAC realism per (scene, method).

Reads ``DIR/manifest.json`` and ``DIR/rollouts/<method>/<scenario_id>.parquet`` (written by
``magail-sumo evaluate``), optionally plus external submissions. Every rollout set is checked
against its scene (agent set, 80 steps, finite values); a bad one gives a one-line error naming
the scene / agent and the others are still scored.

Per (scene, method) the realism features are computed once and give both the scene's fields
and the per-agent rows (:func:`agent_metrics`); the log's own features are computed once per
scene for all its methods (:class:`LogFeatures`). The states a method marks invalid (``valid``
column; log replay where the log has none) are kept as a mask so figures never draw them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from converters import find_scene, iter_scenes
from magail_sumo.errors import MagailSumoError
from magail_sumo.evaluation.realism.config import CHALLENGE_2025, Bernoulli, Histogram
from magail_sumo.evaluation.realism.estimators import (
    bernoulli_log_likelihood, histogram_log_likelihood,
)
from magail_sumo.evaluation.realism.metrics import (
    _FLAGS, _MASKS, Features, compute_features, feature_masks, log_features,
    metrics_from_features, value_name,
)
from magail_sumo.evaluation.realism.trajectories import JointTrajectories, joint_trajectories
from magail_sumo.evaluation.protocol import N_STEPS
from magail_sumo.evaluation.storage import read_manifest, read_rollouts_valid, rollouts_path
from magail_sumo.evaluation.submission import (
    ScenarioRollouts, SubmissionError, iter_submission, validate_rollouts,
)
from magail_sumo.evaluation.traffic import MetricInput, compute_metrics
from magail_sumo.evaluation.traffic.events import log_offroad
from magail_sumo.evaluation.traffic.distributions import BINS
from magail_sumo.outputs import OutputError, printable
from magail_sumo.scene import ObjectType, Scene
from magail_sumo.workers import Progress, no_progress, run_jobs

from .intervals import mean_ci
from . import animation, figures
from .scores import SceneView, Scores


#: Per-agent columns of :func:`agent_metrics` (after scenario_id, method, object_id, type).
AGENT_FIELDS = [f"{fc.name}_likelihood" for fc in CHALLENGE_2025.features] + [
    "ade", "min_ade", "collision_rate", "offroad_rate"]


def agent_metrics(feat: Features, config=CHALLENGE_2025) -> dict[str, np.ndarray]:
    """Per evaluated agent (E,): each realism feature's likelihood (histogram features: exp of
    the mean log-likelihood over that agent's masked steps, NaN where it has none; Bernoulli
    features: the likelihood of its logged flag), ADE and minADE over rollouts (m), and the
    share of rollouts in which it collides / goes off-road — the per-agent parts of
    :func:`~magail_sumo.evaluation.realism.metrics.metrics_from_features` (NaN road-edge
    fields on a map without road edges)."""
    masks, flag_mask = feature_masks(feat)
    out: dict[str, np.ndarray] = {}
    flags = {}
    with np.errstate(invalid="ignore", divide="ignore"):
        for fc in config.features:
            if value_name(fc) not in feat.values:  # a road-edge feature of a map without edges
                out[f"{fc.name}_likelihood"] = np.full(len(feat.object_id), np.nan)
            elif isinstance(fc.estimator, Histogram):
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
    out["offroad_rate"] = flags["offroad_indication"][1:].mean(0) \
        if "offroad_indication" in flags else np.full(len(feat.object_id), np.nan)
    return out


def load_scenes(manifest: dict, errors: list[str]) -> dict[str, Scene]:
    """The manifest's scenes, read from their files (missing ones reported)."""
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


def _eval_subset(feat: Features, n_eval: int) -> Features:
    """The features of the first ``n_eval`` agents (the evaluated ones): every feature of an
    agent depends only on its own row against all objects, so this equals computing the
    realism features with ``n_eval`` evaluated agents."""
    return Features(feat.object_id[:n_eval], feat.is_vehicle[:n_eval], feat.valid[:n_eval],
                    {k: v[:, :n_eval] for k, v in feat.values.items()},
                    feat.displacement[:, :n_eval], feat.log_valid_all[:n_eval])


#: Features whose log / rollout histograms the report's distribution figure pools over scenes.
FIGURE_FEATURES = ("linear_speed", "linear_acceleration", "time_to_collision")


def _counts(values: np.ndarray, feature: str) -> np.ndarray:
    """Histogram counts of ``values`` on the feature's bins (as
    :func:`~magail_sumo.evaluation.traffic.distributions.histogram`, not normalised)."""
    lo, hi, n = BINS[feature]
    edges = np.linspace(lo, hi, n + 1)
    idx = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, n - 1)
    return np.bincount(idx, minlength=n).astype(np.int64)


@dataclass
class PairScore:
    """The scores of one (scene, method): its metrics row, its per-agent rows and the
    histogram counts of :data:`FIGURE_FEATURES`; or the one-line ``error``."""

    scenario_id: str
    method: str
    row: dict | None = None
    agent_rows: list[dict] = field(default_factory=list)
    counts: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    error: str | None = None


class LogFeatures:
    """The realism features of one scene's log (:func:`~magail_sumo.evaluation.realism.
    metrics.log_features`), computed for the first rollout set scored and reused for the
    scene's other methods."""

    def __init__(self) -> None:
        self._key: tuple | None = None
        self._values: dict[str, np.ndarray] | None = None

    def of(self, scene: Scene, jt: JointTrajectories, config) -> dict[str, np.ndarray]:
        """The log's features for ``jt`` (computed anew should its agents differ)."""
        key = (scene.scenario_id, config.current_time_index, jt.n_eval, jt.object_id.tobytes())
        if self._values is None or key != self._key:
            self._key, self._values = key, log_features(scene, jt, config)
        return self._values


def score_pair(scene: Scene, method: str, ro: ScenarioRollouts,
               log: LogFeatures | None = None) -> PairScore:
    """Validate and score one rollout set; never raises (a failure is ``error``).

    The features of all sim agents are computed once (the traffic metrics need them all) and
    the realism fields use the evaluated agents' rows; the simulated steps start after the
    scene's own current step (a scene recorded with another history length is scored on its
    80 simulated steps like any other).

    :param log: the scene's :class:`LogFeatures`, shared by its methods (None: the log's
        features are computed with the rollouts')."""
    sid = scene.scenario_id
    res = PairScore(sid, method)
    try:
        validate_rollouts(ro, scene, ro.shape[0], N_STEPS)
        config = CHALLENGE_2025
        if scene.current_time_index != config.current_time_index:
            config = dataclasses.replace(config, current_time_index=scene.current_time_index)
        jt = joint_trajectories(scene, ro)
        n_eval = jt.n_eval
        jt = dataclasses.replace(jt, n_eval=len(jt.object_id))
        feat_all = compute_features(scene, jt, config,
                                    None if log is None else log.of(scene, jt, config))
        feat = _eval_subset(feat_all, n_eval)
        realism = metrics_from_features(feat, config)
        per_agent = agent_metrics(feat, config)
        fut = slice(scene.current_time_index + 1, None)
        inp = MetricInput(scene, jt, feat_all, jt.x[..., fut], jt.y[..., fut],
                          jt.heading[..., fut], jt.log_valid[:, fut],
                          jt.object_type == int(ObjectType.VEHICLE))
        traffic = compute_metrics(inp)
        log_rate, log_count = log_offroad(inp)
        for name in FIGURE_FEATURES:
            lv, sv = inp.log_and_sim(name)
            res.counts[name] = (_counts(lv, name), _counts(sv, name))
    except SubmissionError as exc:
        res.error = f"method {method}: {exc}"
        return res
    except ValueError as exc:
        res.error = f"method {method}: scenario {printable(sid)}: {exc}"
        return res
    except Exception as exc:  # noqa: BLE001 - one scene's failure, the others are scored
        res.error = (f"method {method}: scenario {printable(sid)}: cannot score "
                     f"({type(exc).__name__}: {' '.join(str(exc).split())[:300]})")
        return res
    res.row = {"scenario_id": sid, "method": method, "rollouts": ro.shape[0],
               **traffic, **realism, "log_offroad_rate": log_rate,
               "log_offroad_vehicles": log_count}
    tr = scene.tracks
    for k, oid in enumerate(feat.object_id):
        row = int(np.flatnonzero(tr.id == oid)[0])
        res.agent_rows.append({
            "scenario_id": sid, "method": method, "object_id": int(oid),
            "type": ObjectType(int(tr.type[row])).name.lower(),
            "sdc": row == scene.sdc_track_index,
            **{f: float(per_agent[f][k]) for f in AGENT_FIELDS}})
    return res


def _add(scores: Scores, res: PairScore, ro: ScenarioRollouts,
         valid: np.ndarray | None) -> None:
    if res.error is not None:
        scores.errors.append(res.error)
        return
    key = (res.scenario_id, res.method)
    scores.rows.append(res.row)  # type: ignore[arg-type]
    scores.agent_rows.extend(res.agent_rows)
    scores.counts[key] = res.counts
    scores.rollouts[key] = ro
    if valid is not None:
        scores.valid[key] = valid
    if res.method not in scores.methods:
        scores.methods.append(res.method)


def score(scores: Scores, sid: str, method: str, ro: ScenarioRollouts,
          valid: np.ndarray | None = None, log: LogFeatures | None = None) -> None:
    """Validate and score one rollout set into ``scores`` (errors are recorded, not raised;
    ``log``: the scene's :class:`LogFeatures`)."""
    _add(scores, score_pair(scores.scenes[sid], method, ro, log), ro, valid)


def _read_pair(folder: Path, method: str, scene: Scene
               ) -> tuple[ScenarioRollouts, np.ndarray | None] | str:
    """The rollouts and valid mask of (method, scene), or a one-line error."""
    sid = scene.scenario_id
    try:
        path = rollouts_path(folder, method, sid)
    except OutputError as exc:
        return f"method {printable(method)}: {exc}"
    if not path.is_file():
        return f"method {printable(method)}: scenario {printable(sid)}: no rollouts ({path})"
    try:
        return read_rollouts_valid(path, scene)
    except MagailSumoError as exc:
        return f"method {method}: {' '.join(str(exc).split())}"


def scene_view(scores: Scores, sid: str) -> SceneView:
    """The trajectory figure and animation of one scene of ``scores``."""
    methods = tuple(m for m in scores.methods if (sid, m) in scores.rollouts)
    return SceneView(methods, figures.trajectories(scores, sid),
                     animation.scene_animation(scores, sid))


#: A scoring job: the folder, then per scene (scene file, scenario id, methods, whether to draw
#: its view: the job scores all the folder's methods of it).
ScoreJob = tuple[str, list[tuple[str, str, list[str], bool]]]


def _score_job(job: ScoreJob) -> list[tuple[list[tuple], SceneView | None]]:
    """Worker: score the given methods of the given scenes (read from their files) of a folder
    and draw the views asked for.

    :returns: per scene, (per method ``("ok", PairScore, rollouts, valid)`` or ``("error",
        message)``; its :class:`SceneView` or None)."""
    folder, units = job
    out: list[tuple[list[tuple], SceneView | None]] = []
    for scene_file, sid, methods, draw in units:
        scene = find_scene(scene_file, sid)
        part = Scores({}, {sid: scene}, [])
        items: list[tuple] = []
        log = LogFeatures()
        for m in methods:
            got = _read_pair(Path(folder), m, scene)
            if isinstance(got, str):
                items.append(("error", got))
            else:
                items.append(("ok", score_pair(scene, m, got[0], log), *got))
                _add(part, *items[-1][1:])
        view = None
        if draw and part.methods:
            try:
                view = scene_view(part, sid)
            except Exception:  # noqa: BLE001 - the report draws it again (and reports that)
                view = None
        out.append((items, view))
    return out


def plan_jobs(costs: dict[str, float], methods: list[str], workers: int
              ) -> list[list[tuple[str, list[str]]]]:
    """(scene, methods) units in at most ``workers`` jobs of about equal cost (largest first,
    each to the least loaded job): whole scenes when there are at least as many scenes as
    workers, else each scene's methods split in as many parts as it takes.

    :param costs: per scenario id, the relative cost of scoring one of its methods (e.g. the
        number of sim agents)."""
    parts = 1 if len(costs) >= workers else -(-workers // max(1, len(costs)))
    per = max(1, -(-len(methods) // parts))
    units = [(sid, methods[i:i + per]) for sid in costs for i in range(0, len(methods), per)]
    units.sort(key=lambda u: -costs[u[0]] * len(u[1]))  # stable: ties keep scene order
    jobs: list[list[tuple[str, list[str]]]] = [[] for _ in range(min(workers, len(units)))]
    load = [0.0] * len(jobs)
    for sid, ms in units:
        k = load.index(min(load))
        jobs[k].append((sid, ms))
        load[k] += costs[sid] * len(ms)
    return jobs


def _agents(entry: dict) -> float:
    """A manifest scene entry's number of sim agents (0 when absent or not a number)."""
    n = entry.get("agents")
    return float(n) if isinstance(n, (int, float)) and math.isfinite(n) and n > 0 else 0.0


#: what every scoring process imports (the report package: scoring, figures, the metrics):
#: imported once by the process they are forked from (:func:`magail_sumo.workers.run_jobs`'
#: ``preload``), not once per worker (about 1.5 s each)
SCORING_IMPORTS = ("magail_sumo.evaluation.report",)


def default_workers() -> int:
    """Scoring processes by default: up to 2, one per core."""
    import os

    return max(1, min(2, os.cpu_count() or 1))


def collect(folder: str | Path, submissions: dict[str, list[str]] | None = None,
            workers: int | None = None, progress: Progress = no_progress) -> Scores:
    """Score every method and scene of an evaluation folder, plus named external submissions
    (``{method name: [submission files]}``; a scenario not among the folder's scenes is an
    error).

    :param workers: > 1: the (scene, method) pairs are scored in that many worker processes
        (:func:`magail_sumo.workers.run_jobs`; jobs of a few methods of one scene each); the
        result is the same as in-process scoring (default :func:`default_workers`).
    :param progress: told ``("scored", done, total)`` as (scene, method) pairs are scored."""
    folder = Path(folder)
    manifest = read_manifest(folder)
    errors: list[str] = []
    scenes = load_scenes(manifest, errors)
    scores = Scores(manifest, scenes, [], errors=errors)
    methods = list(manifest.get("methods", []))
    workers = default_workers() if workers is None else max(1, int(workers))
    results: dict[tuple[str, str], tuple] = {}
    logs = {sid: LogFeatures() for sid in scenes}  # each scene's log features, once
    if workers > 1 and len(scenes) * len(methods) > 1:
        entries = {s["scenario_id"]: s for s in manifest.get("scenes", [])}
        # one job per worker (a worker's start-up, imports and compiled kernels cost seconds),
        # balanced by the scenes' sim agents; a whole scene's job also draws its view
        costs = {sid: 1.0 + _agents(entries[sid]) for sid in scenes}
        jobs = [(str(folder), [(entries[sid]["file"], sid, ms, len(ms) == len(methods))
                               for sid, ms in units])
                for units in plan_jobs(costs, methods, workers)]
        total, done = len(scenes) * len(methods), 0
        for res in run_jobs(_score_job, jobs, workers=workers, preload=SCORING_IMPORTS):
            done += sum(len(u[2]) for u in res.job[1])
            progress("scored", done, total)
            for k, (_, sid, ms, _) in enumerate(res.job[1]):
                items, view = res.value[k] if res.ok else (
                    [("error", f"method {printable(m)}: scenario {printable(sid)}: cannot "
                               f"score ({res.reason})") for m in ms], None)
                results.update({(m, sid): item for m, item in zip(ms, items)})
                if view is not None:
                    scores.views[sid] = view
    total = len(scenes) * len(methods)
    scored = sum(1 for m in methods for sid in scenes if (m, sid) in results)  # by the workers
    for method in methods:
        for sid in scenes:
            if (method, sid) in results:
                item = results.pop((method, sid))
            else:
                got = _read_pair(folder, method, scenes[sid])
                item = ("error", got) if isinstance(got, str) else \
                    ("ok", score_pair(scenes[sid], method, got[0], logs[sid]), *got)
                scored += 1
                progress("scored", scored, total)
            if item[0] == "error":
                scores.errors.append(item[1])
            else:
                _add(scores, *item[1:])
    for method, files in (submissions or {}).items():
        try:
            for rec in iter_submission(files):
                if rec.error is not None:
                    scores.errors.append(f"method {method}: {rec.error}")
                elif rec.scenario_id not in scenes:
                    scores.errors.append(f"method {method}: scenario {rec.scenario_id}: not "
                                         "among the evaluated scenes")
                else:
                    score(scores, rec.scenario_id, method, rec.rollouts,  # type: ignore[arg-type]
                          log=logs[rec.scenario_id])
        except SubmissionError as exc:
            scores.errors.append(f"method {method}: {exc}")
    return scores


def method_intervals(scores: Scores, fields: list[str]) -> dict[str, dict[str, float]]:
    """Per method, the half-width of the 95 % interval of each field's mean over its scored
    scenes (:func:`~.intervals.mean_ci`; NaN with fewer than two finite values)."""
    out = {}
    for m in scores.methods:
        rows = [r for r in scores.rows if r["method"] == m]
        out[m] = {f: mean_ci([r[f] for r in rows])[1] for f in fields}
    return out


def method_means(scores: Scores, fields: list[str]) -> dict[str, dict[str, float]]:
    """Per method, the mean over its scored scenes of each field (NaN-aware)."""
    out = {}
    for m in scores.methods:
        rows = [r for r in scores.rows if r["method"] == m]
        out[m] = {f: float(np.nanmean([r[f] for r in rows])) if any(
            np.isfinite(r[f]) for r in rows) else float("nan") for f in fields}
    return out
