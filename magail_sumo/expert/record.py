"""Record expert demonstrations: replay the log through the same sensors as training.

Each scene runs in :class:`~magail_sumo.env.driving_env.SumoDrivingEnv` with every route vehicle
controlled, driven by :func:`~magail_sumo.env.log_actions.expert_actions`
(:class:`~magail_sumo.agents.LogReplayPolicy` through :func:`magail_sumo.agents.rollout`) under
:data:`~magail_sumo.env.log_actions.REPLAY_LIMITS` (wide enough to follow the recorded tracks), no
terminating events, log background. Per vehicle and step the Parquet file stores ``s``,
``s_next`` (the observation before and after the step), ``action`` — the inverse-dynamics
acceleration and steering normalised with the *training* limits and clipped to [-1, 1], i.e.
the action a policy would have to output — the physical ``accel`` (m/s²) and ``steer`` (rad),
``done`` (the vehicle left after this step), ``scene_id`` / ``track_id`` / ``step``, and the
vehicle's pose at the step of ``s``: ``x``, ``y`` (m) and ``yaw`` (rad, counter-clockwise from
+x), scene frame, float64 (its bicycle state, as the env reports it for policy vehicles;
format ``/2``, which the decomposed discriminator needs — format ``/1`` files lack them). The
previous-action entries of the observation (``prev_accel``, ``prev_steer``) are rewritten to
those training-normalised actions, so expert and policy observations share one scale.

``DIR/<scenario_id>.parquet`` per scene plus ``DIR/metadata.json``: the format, the observation
layout (``observation_names``), the observation config with its hash (``observation_hash``,
:func:`observation_hash`: every field, sensor ranges included; training refuses data recorded
with another) and the training limits. The file name
is :func:`magail_sumo.outputs.safe_name` of the scenario id (the id itself for every real WOMD
id); ``metadata.json`` (``scenes[].scenario_id`` / ``parquet``) and the ``scene_id`` column keep
the original id. ``DIR`` must be new, empty or written by magail_sumo
(:func:`~magail_sumo.outputs.claim_output_dir`); every file is written atomically.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from magail_sumo.agents import LogReplayPolicy, Step, rollout
from magail_sumo.config import to_dict
from magail_sumo.env import REPLAY_LIMITS, SumoDrivingEnv
from magail_sumo.env.config import EnvConfig
from magail_sumo.env.log_actions import training_actions
from magail_sumo.env.slot_worker import SceneSpec, load_spec_scene
from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import (NameRegistry, atomic_path, claim_output_dir, inside, printable,
                                 safe_name, write_text)
from magail_sumo.sensors.observation import ObservationConfig, observation_names
from magail_sumo.sim.dynamics import BicycleLimits
from magail_sumo.workers import run_jobs

EXPERT_FORMAT = "magail_sumo.expert/2"
#: formats :class:`~magail_sumo.expert.dataset.ExpertDataset` reads (``/1``: no poses)
READABLE_FORMATS = ("magail_sumo.expert/1", EXPERT_FORMAT)


def observation_hash(observation: ObservationConfig) -> str:
    """SHA-256 (hex) of every field of an observation config (:func:`~magail_sumo.config.
    to_dict`, keys sorted): two configs hash alike exactly when every field, sensor ranges and
    beam counts included, is the same."""
    text = json.dumps(to_dict(observation), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def _fixed_list(values: np.ndarray):
    import pyarrow as pa

    values = np.ascontiguousarray(values, np.float32)
    return pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1)), values.shape[1])


def record_scene(spec: SceneSpec, observation: ObservationConfig, limits: BicycleLimits,
                 out_dir: str | Path, seed: int = 0) -> dict:
    """Replay one scene and write ``out_dir/<id>.parquet``; a summary dict of the scene.

    Call in a process of its own (libsumo: one simulation per process)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    scene = load_spec_scene(spec)
    cfg = EnvConfig(controlled="all", background="log", terminate_on=(), observation=observation,
                    limits=REPLAY_LIMITS)
    env = SumoDrivingEnv(scene, spec.bundle, cfg)
    names = observation_names(observation)
    prev = [names.index(n) for n in ("prev_accel", "prev_steer") if n in names]
    cols: dict[str, list] = {k: [] for k in ("track", "step", "done", "s", "s_next", "action",
                                             "accel", "steer", "pose")}
    expert = LogReplayPolicy()

    def keep(step: Step) -> None:
        st = expert.states  # poses at the step of s; the actions' keys follow st.names
        pose = np.stack([st.state.x, st.state.y, st.state.yaw], axis=1)
        names_now = list(step.actions)
        raw = np.stack([step.actions[a] for a in names_now]).astype(np.float64)
        a_train, accel, steer = training_actions(raw, limits)
        s = np.stack([step.observations[a] for a in names_now]).astype(np.float32)
        s_next = np.stack([step.next_observations[a] for a in names_now]).astype(np.float32)
        if len(prev) == 2:  # the next step's s sees the rewritten entries too
            s_next[:, prev] = a_train
            for i, a in enumerate(names_now):
                step.next_observations[a] = s_next[i]
        cols["track"].append(np.array([int(a) for a in names_now], np.int64))
        cols["step"].append(np.full(len(names_now), step.t, np.int32))
        cols["done"].append(np.array([bool(step.terminations[a] or step.truncations[a])
                                      for a in names_now]))
        cols["s"].append(s)
        cols["s_next"].append(s_next)
        cols["action"].append(a_train)
        cols["accel"].append(np.asarray(accel, np.float32))
        cols["steer"].append(np.asarray(steer, np.float32))
        cols["pose"].append(pose.astype(np.float64))

    try:
        rollout(env, expert, keep, seed=seed)
    finally:
        env.close()
    width = {"action": 2, "pose": 3}
    cat = {k: (np.concatenate(v) if v else np.zeros((0,) if k in ("track", "step", "done",
                                                                  "accel", "steer")
                                                     else (0, width.get(k, len(names))),
                                                     np.float32))
           for k, v in cols.items()}
    n = len(cat["track"])
    table = pa.table({
        "scene_id": pa.array([scene.scenario_id] * n, pa.string()),
        "track_id": pa.array(cat["track"].astype(np.int64)),
        "step": pa.array(cat["step"].astype(np.int32)),
        "done": pa.array(cat["done"].astype(bool)),
        "s": _fixed_list(cat["s"].reshape(n, len(names))),
        "s_next": _fixed_list(cat["s_next"].reshape(n, len(names))),
        "action": _fixed_list(cat["action"].reshape(n, 2)),
        "accel": pa.array(cat["accel"].astype(np.float32)),
        "steer": pa.array(cat["steer"].astype(np.float32)),
        "x": pa.array(cat["pose"][:, 0].astype(np.float64)),
        "y": pa.array(cat["pose"][:, 1].astype(np.float64)),
        "yaw": pa.array(cat["pose"][:, 2].astype(np.float64)),
    })
    out = inside(out_dir, f"{safe_name(scene.scenario_id)}.parquet")
    with atomic_path(out) as tmp:
        pq.write_table(table, tmp)
    return {"scenario_id": scene.scenario_id, "file": str(spec.scene_file), "rows": n,
            "steps": int(len(np.unique(cat["step"]))), "vehicles": int(len(np.unique(cat["track"]))),
            "parquet": out.name}


def _record_job(args: tuple) -> dict:
    return record_scene(*args)


#: seconds one scene's recording may take by default before its worker is killed
DEFAULT_TIMEOUT_S = 1800.0


def record_expert(specs: Sequence[SceneSpec], out_dir: str | Path,
                  observation: ObservationConfig | None = None,
                  limits: BicycleLimits | None = None, workers: int = 1, seed: int = 0,
                  on_scene: Callable[[dict], None] | None = None,
                  on_error: Callable[[SceneSpec, str], None] | None = None,
                  timeout_s: float | None = DEFAULT_TIMEOUT_S) -> dict:
    """Record every scene (each in a fresh process) into ``out_dir``; the metadata written.

    A scene that fails (raises, its worker dies, or runs longer than ``timeout_s`` seconds:
    killed) is left out, listed under ``failed`` in the metadata (only when there is one) and
    passed to ``on_error`` with a one-line reason; the other scenes go on. Without
    ``on_error``, :class:`~magail_sumo.errors.MagailSumoError` is raised at the end (after the
    metadata is written) naming the first failure.

    :param on_scene: called with each scene's summary as soon as it is written (in order).
    """
    observation = observation or ObservationConfig()
    limits = limits or BicycleLimits()
    out = claim_output_dir(out_dir, "expert", ["metadata.json"])
    meta_path = inside(out, "metadata.json")  # a link out of the folder: refused before recording
    names = NameRegistry()  # two scenes on one file name: refused before any is recorded
    parquets = [f"{names.name(spec.name if spec.scenario_id is None else spec.scenario_id)}"
                ".parquet" for spec in specs]
    jobs = [(spec, observation, limits, out, seed) for spec in specs]
    scenes, failed = [], []
    for res in run_jobs(_record_job, jobs, workers=max(1, min(workers, len(jobs) or 1)),
                        timeout_s=timeout_s, ordered=True):
        if res.ok:
            scenes.append(res.value)
            if on_scene is not None:
                on_scene(res.value)
            continue
        spec = res.job[0]
        reason = f"scene {printable(spec.name)} ({spec.scene_file}): {res.reason}"
        failed.append({"scenario_id": spec.name, "file": str(spec.scene_file), "reason": reason})
        if on_error is not None:
            on_error(spec, reason)
    meta = {"format": EXPERT_FORMAT, "observation_names": observation_names(observation),
            "observation": to_dict(observation),
            "observation_hash": observation_hash(observation), "limits": to_dict(limits),
            "action": ["accel", "steer"], "scenes": scenes}
    if failed:
        meta["failed"] = failed
    claim_output_dir(out, "expert", ["metadata.json", *parquets])
    write_text(meta_path, json.dumps(meta, indent=2))
    if failed and on_error is None:
        raise MagailSumoError(f"{len(failed)} of {len(jobs)} scene(s) not recorded; first: "
                              f"{failed[0]['reason']}")
    return meta
