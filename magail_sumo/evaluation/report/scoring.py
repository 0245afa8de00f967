"""Scores of an evaluation folder: traffic metrics and WOSAC realism per (scene, method).

Reads ``DIR/manifest.json`` and ``DIR/rollouts/<method>/<scenario_id>.parquet`` (written by
``magail-sumo evaluate``), optionally plus external submissions. Every rollout set is checked
against its scene (agent set, 80 steps, finite values); a bad one gives a one-line error naming
the scene / agent and the others are still scored.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from magail_sumo.errors import MagailSumoError
from magail_sumo.evaluation.realism import scenario_metrics
from magail_sumo.evaluation.rollouts import N_STEPS, read_manifest, read_rollouts, rollouts_path
from magail_sumo.evaluation.submission import (
    ScenarioRollouts, SubmissionError, iter_submission, validate_rollouts,
)
from magail_sumo.evaluation.traffic import MetricInput, compute_metrics
from magail_sumo.outputs import OutputError, printable
from magail_sumo.scene import Scene


@dataclass
class Scores:
    """Everything a report shows.

    :param rows: one dict per (scenario_id, method): traffic metrics and realism fields.
    :param inputs: the metric inputs (features) per (scenario_id, method), for figures.
    :param rollouts: the rollouts per (scenario_id, method).
    :param errors: one-line problems (scene / method / agent named).
    """

    manifest: dict
    scenes: dict[str, Scene]
    methods: list[str]
    rows: list[dict] = field(default_factory=list)
    inputs: dict[tuple[str, str], MetricInput] = field(default_factory=dict)
    rollouts: dict[tuple[str, str], ScenarioRollouts] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)


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


def score(scores: Scores, sid: str, method: str, ro: ScenarioRollouts) -> None:
    """Validate and score one rollout set (errors are recorded, not raised)."""
    scene = scores.scenes[sid]
    try:
        validate_rollouts(ro, scene, ro.shape[0], N_STEPS)
        realism = scenario_metrics(scene, ro, validate=False)
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
            except MagailSumoError as exc:
                scores.errors.append(f"method {method}: {' '.join(str(exc).split())}")
                continue
            score(scores, sid, method, ro)
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
