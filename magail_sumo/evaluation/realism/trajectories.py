"""Agent selection and the joint 91-step trajectories the realism features are computed on.

Every rollout is the log's history (steps ``0..current``) followed by its simulated steps. Box
sizes after the current step are the log's sizes *at* the current step, for rollouts and for the
log alike; log states are used exactly as stored, invalid ones included. All geometry is float32
(metres, scene frame; headings radians CCW from +x), as in the official tool.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magail_sumo.evaluation.submission import ScenarioRollouts, sim_agent_ids
from magail_sumo.scene import Scene

__all__ = ["JointTrajectories", "evaluated_ids", "joint_trajectories", "log_replay",
           "sim_agent_ids"]


def evaluated_ids(scene: Scene) -> np.ndarray:
    """Ascending ids of the scored objects: the SDC plus the tracks to predict."""
    tr = scene.tracks
    idx = {scene.sdc_track_index} | {p.track_index for p in scene.tracks_to_predict}
    return np.unique(tr.id[sorted(i for i in idx if i >= 0)]).astype(np.int64)


@dataclass(frozen=True, eq=False)
class JointTrajectories:
    """Batched trajectories of all sim agents, evaluated agents first.

    Batch row 0 is the log, rows 1.. the rollouts (B = 1 + R).

    :param object_id: (A,) int64 ids; the first ``n_eval`` are the evaluated agents (ascending).
    :param object_type: (A,) int8 ObjectType.
    :param x, y, z, heading: (B, A, T) float32.
    :param length, width, height: (A, T) float32 box sizes (shared by all batch rows).
    :param valid: (B, A, T) bool; the log's validity in row 0, history validity then True in
        the rollout rows.
    :param log_valid: (A, T) bool, the log's validity (the evaluation mask).
    """

    object_id: np.ndarray
    object_type: np.ndarray
    n_eval: int
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    heading: np.ndarray
    length: np.ndarray
    width: np.ndarray
    height: np.ndarray
    valid: np.ndarray
    log_valid: np.ndarray


def joint_trajectories(scene: Scene, ro: ScenarioRollouts) -> JointTrajectories:
    """Log plus rollouts as 91-step arrays; ``ro`` must already be validated against ``scene``."""
    tr = scene.tracks
    cur = scene.current_time_index
    ev = evaluated_ids(scene)
    sim = sim_agent_ids(scene)
    order = np.concatenate([ev, sim[~np.isin(sim, ev)]])
    row = {int(i): k for k, i in enumerate(tr.id.tolist())}
    idx = np.array([row[int(i)] for i in order])
    col = {int(i): k for k, i in enumerate(ro.object_id.tolist())}
    sub = np.array([col[int(i)] for i in order])
    R, T = ro.x.shape[0], cur + 1 + ro.x.shape[2]

    def batch(log: np.ndarray, sim_vals: np.ndarray) -> np.ndarray:
        log = log[idx, :T].astype(np.float32)
        out = np.empty((R + 1,) + log.shape, np.float32)
        out[0] = log
        out[1:, :, :cur + 1] = log[None, :, :cur + 1]
        out[1:, :, cur + 1:] = sim_vals[:, sub]
        return out

    def sizes(a: np.ndarray) -> np.ndarray:
        a = a[idx, :T].astype(np.float32)
        a[:, cur + 1:] = a[:, cur:cur + 1]
        return a

    log_valid = tr.valid[idx, :T]
    valid = np.empty((R + 1,) + log_valid.shape, bool)
    valid[0] = log_valid
    valid[1:, :, :cur + 1] = log_valid[None, :, :cur + 1]
    valid[1:, :, cur + 1:] = True
    return JointTrajectories(
        object_id=order, object_type=tr.type[idx], n_eval=len(ev),
        x=batch(tr.x, ro.x), y=batch(tr.y, ro.y), z=batch(tr.z, ro.z),
        heading=batch(tr.heading, ro.heading), length=sizes(tr.length), width=sizes(tr.width),
        height=sizes(tr.height), valid=valid, log_valid=log_valid)


def log_replay(scene: Scene, n_rollouts: int = 32, n_steps: int = 80) -> ScenarioRollouts:
    """``n_rollouts`` copies of the logged future of every sim agent (stored values, invalid
    states included), as the official log-replay joint scene."""
    tr = scene.tracks
    cur = scene.current_time_index
    ids = sim_agent_ids(scene)
    rows = np.isin(tr.id, ids)
    fut = slice(cur + 1, cur + 1 + n_steps)

    def rep(a: np.ndarray) -> np.ndarray:
        return np.repeat(a[rows, fut].astype(np.float32)[None], n_rollouts, 0)

    return ScenarioRollouts(scene.scenario_id, ids, rep(tr.x), rep(tr.y), rep(tr.z),
                            rep(tr.heading))
