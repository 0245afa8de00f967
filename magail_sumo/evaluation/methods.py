"""How each method produces the simulated steps of a scene (the protocol:
:mod:`magail_sumo.evaluation.protocol`). Methods:

* ``logreplay``: the recorded future (stored states, invalid ones included).
* ``constvel``: constant velocity from the recorded state at the current step (heading held).
* ``sumo``: SUMO's default car-following (Krauss) drives the converted routes from every route
  vehicle's recorded pose and speed at the current step, each with a seeded speed factor; every
  other sim agent moves at constant velocity and is an obstacle SUMO's drivers brake for
  (:mod:`magail_sumo.agents.sumo_baseline` has the details).
* a policy (``random``, or a checkpoint / ``module:factory`` spec, see
  :func:`magail_sumo.policies.make_policy`): drives every route vehicle and cyclist through
  :class:`~magail_sumo.env.SumoDrivingEnv` (bicycle model, log background, no event
  terminates an agent; :func:`magail_sumo.agents.rollout`), built with the policy's
  ``observation``, ``action_layout`` and gap ``guard`` when it names them. Rollout ``r`` runs
  with the policy as ``make_policy(spec, rollout_seed(seed, r), ...)`` builds it; a training
  checkpoint samples its actions from that seed (``deterministic=True``: the tanh of the
  Gaussian mean, the same in every rollout).

A policy that acts for many worlds at once (``reseed_worlds`` / ``act_worlds``:
:func:`~magail_sumo.agents.batched`; training checkpoints, ``pretrained``, ``random``) runs all
the rollouts of a batch at once in the batched core (:func:`batched_rollouts`: one
:class:`~magail_sumo.env.batched.BatchedSceneEnv` world per rollout, one forward pass per step
for all of them). Any other policy runs its rollouts one after another through one env and one
policy (:class:`PolicyRollouts`): the env is reset with each rollout's seed and the policy
reseeded (its optional ``reseed(seed)``, :class:`~magail_sumo.agents.base.Policy`) rather
than both rebuilt, which gives the same rollouts as a fresh env and policy per rollout; a
policy without ``reseed`` (a user's factory) is built anew per rollout.

Objects a method does not move (pedestrians, objects SUMO does not carry, vehicles not yet
inserted) and objects that leave the simulation early (arrived at their route end, end of
their recorded track in the env) follow the constant-velocity model from their last simulated
(else recorded) state. Positions are box centres in the scene frame (m), headings rad CCW
from +x; z is the recorded z at the current step (SUMO is 2-D).

SUMO methods run one simulation after another in the calling process; the runner gives every
batch of them a fresh worker process (libsumo allows one simulation per process and
has crashed when a second one starts after vehicle removals).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from converters.scene_files import find_scene
from magail_sumo.agents import Policy, batched, env_settings, rollout, rollout_worlds
from magail_sumo.agents import constant_velocity as _cv
from magail_sumo.agents.constant_velocity import Track, current_state, fill_constant_velocity
from magail_sumo.agents.sumo_baseline import sumo_rollouts
from magail_sumo.env import EnvConfig, SumoDrivingEnv
from magail_sumo.env.batched import BatchedSceneEnv
from magail_sumo.env.actions import action_summary
from magail_sumo.errors import MagailSumoError
from magail_sumo.evaluation.protocol import N_STEPS, EvaluationError, log, rollout_seed, span
from magail_sumo.evaluation.realism import log_replay
from magail_sumo.evaluation.submission import ScenarioRollouts, sim_agent_ids
from magail_sumo.outputs import printable
from magail_sumo.scene import Scene
from magail_sumo.sim.dynamics import wrap_angle

#: methods evaluation runs in its own process (no SUMO, no policy)
IN_PROCESS = ("logreplay", "constvel")

Trajectory = tuple[np.ndarray, np.ndarray, np.ndarray]  #: (x, y, yaw), each (A, N_STEPS)


def needs_worker(spec: str) -> bool:
    """Whether method ``spec`` runs SUMO (the runner gives it worker processes)."""
    return spec not in IN_PROCESS


# ------------------------------------------------------------------------- trajectory models
def constant_velocity(scene: Scene, ids: np.ndarray) -> Trajectory:
    """(x, y, yaw) (A, :data:`N_STEPS`): recorded state at the current step moved at its
    velocity (:func:`magail_sumo.agents.constant_velocity.constant_velocity`)."""
    return _cv.constant_velocity(scene, ids, N_STEPS)


def as_rollouts(scene: Scene, ids: np.ndarray, xs: list, ys: list, yaws: list
                ) -> ScenarioRollouts:
    """Rollouts of the per-rollout (x, y, yaw) lists, z held at the current step's."""
    _, _, _, z0, _, _, _ = current_state(scene, ids)
    x, y, yaw = (np.stack(v).astype(np.float32) for v in (xs, ys, yaws))
    yaw = wrap_angle(yaw).astype(np.float32)
    z = np.broadcast_to(z0.astype(np.float32)[None, :, None], x.shape).copy()
    return ScenarioRollouts(scene.scenario_id, ids.astype(np.int64), x, y, z, yaw)


# ---------------------------------------------------------------------------- policy rollouts
def env_config(scene: Scene, policy: Policy) -> EnvConfig:
    """The env of a policy's rollouts: every route vehicle controlled from the scene's current
    step for :data:`N_STEPS` steps, no event ends an agent, with the policy's
    ``observation``, ``action_layout`` and ``guard`` when it has them; log background without
    the SUMO mirror (nothing of such an episode reads SUMO: the same rollouts, bit for bit,
    without running it)."""
    return EnvConfig(controlled="all", start_step=scene.current_time_index, max_steps=N_STEPS,
                     terminate_on=(), end_of_life=False, sumo_mirror=False,
                     **env_settings(policy))


def policy_rollout(scene: Scene, bundle_dir: Path, policy: Policy, seed: int,
                   counts: dict[str, int] | None = None,
                   env: SumoDrivingEnv | None = None) -> Trajectory:
    """One rollout of ``policy`` driving every route vehicle through SumoDrivingEnv (with the
    policy's ``observation`` config, ``action_layout`` and ``guard`` when it has them, e.g. a
    SAC policy's route command), by :func:`magail_sumo.agents.rollout`. Each agent's simulated
    state at a step is the one the env reports after it (``infos[agent]["state"]``).

    :param counts: the env's ``action_counts`` (missing / unknown / non-finite / clipped
        actions) are added to it.
    :param env: the env to reset with ``seed`` and drive (built with :func:`env_config`; the
        caller closes it); None: one is built for this rollout and closed after it."""
    ids = sim_agent_ids(scene)
    col = {str(int(i)): k for k, i in enumerate(ids)}
    cur = scene.current_time_index
    own = env is None
    if env is None:
        env = SumoDrivingEnv(scene, bundle_dir, env_config(scene, policy))
    track = Track.empty(len(ids), N_STEPS)

    def keep(step) -> None:
        t = step.t - cur  # column of log step step.t + 1
        if not 0 <= t < N_STEPS:
            return
        sel = [(col[n], step.infos[n]["state"]) for n in step.agents if n in col]
        if sel:
            a = np.array([s[0] for s in sel])
            state = np.array([s[1] for s in sel], np.float64)  # (n, 4): x, y, yaw, speed
            track.x[a, t], track.y[a, t] = state[:, 0], state[:, 1]
            track.yaw[a, t], track.speed[a, t] = state[:, 2], state[:, 3]

    try:
        rollout(env, policy, keep, seed=seed, max_steps=N_STEPS, scene=scene)
        if counts is not None:
            for k, v in env.action_counts.items():
                counts[k] = counts.get(k, 0) + v
    finally:
        if own:
            env.close()
    return fill_constant_velocity(scene, ids, track)


def batched_rollouts(scene: Scene, bundle_dir: Path, policy: Policy, seeds: list[int],
                     counts: dict[str, int] | None = None) -> list[Trajectory]:
    """The rollouts of ``policy`` with ``seeds`` all at once: one
    :class:`~magail_sumo.env.batched.BatchedSceneEnv` world per seed (the env of
    :func:`env_config`), driven by :func:`~magail_sumo.agents.rollout_worlds` through the
    env's array API; world ``w`` is the rollout :func:`policy_rollout` gives with
    ``seeds[w]``, bit for bit. Each agent's simulated state at a step is its fleet state after
    it; the rest as :func:`policy_rollout`."""
    ids = sim_agent_ids(scene)
    cur = scene.current_time_index
    env = BatchedSceneEnv(scene, bundle_dir, env_config(scene, policy), worlds=len(seeds))
    col_of = {int(i): k for k, i in enumerate(ids.tolist())}
    # fleet row -> column of its agent (-1: not a sim agent)
    col = np.array([col_of.get(int(a), -1) for a in env.world_agents] * env.worlds, np.int64)
    states = np.full((4, len(seeds), len(ids), N_STEPS), np.nan)

    def keep(t: int, rows: np.ndarray, actions, step) -> None:
        t -= cur  # column of log step t + 1
        rows = rows[col[rows] >= 0]
        if not 0 <= t < N_STEPS or not rows.size:
            return
        fl = env.fleet
        w, a = env.world_of(rows), col[rows]
        states[0, w, a, t], states[1, w, a, t] = fl.x[rows], fl.y[rows]
        states[2, w, a, t], states[3, w, a, t] = fl.yaw[rows], fl.speed[rows]

    try:
        rollout_worlds(env, policy, seeds, keep, max_steps=N_STEPS, scene=scene)
        if counts is not None:
            for k, v in env.action_counts.items():
                counts[k] = counts.get(k, 0) + v
    finally:
        env.close()
    return [fill_constant_velocity(scene, ids, Track(*states[:, w])) for w in range(len(seeds))]


class PolicyRollouts:
    """Rollouts of one policy on one scene through one env (module doc): the policy is built
    once, by ``make(seed)``, and reseeded for every later rollout (its ``reseed(seed)``; built
    anew when it has none); the env is built once, with :func:`env_config`, and reset with each
    rollout's seed (built anew only if a rebuilt policy asks for other env settings).

    Use as a context manager (the env's SUMO session is closed at the end)."""

    def __init__(self, scene: Scene, bundle_dir: str | Path, make: Callable[[int], Policy]
                 ) -> None:
        self.scene, self.bundle_dir, self.make = scene, Path(bundle_dir), make
        self.policy: Policy | None = None
        self.env: SumoDrivingEnv | None = None
        self._settings: dict | None = None

    def policy_for(self, seed: int) -> Policy:
        """The policy as ``make(seed)`` builds it."""
        reseed = getattr(self.policy, "reseed", None)
        if callable(reseed):
            reseed(seed)
        else:
            self.policy = self.make(seed)
        return self.policy  # type: ignore[return-value]

    def env_for(self, policy: Policy) -> SumoDrivingEnv:
        """The env ``policy`` drives (the one built before when its settings are the same)."""
        settings = env_settings(policy)
        if self.env is None or settings != self._settings:
            self.close()
            self.env = SumoDrivingEnv(self.scene, self.bundle_dir, env_config(self.scene, policy))
            self._settings = settings
        return self.env

    def run(self, seed: int, counts: dict[str, int] | None = None) -> Trajectory:
        """One rollout with ``seed`` (:func:`policy_rollout`)."""
        policy = self.policy_for(seed)
        return policy_rollout(self.scene, self.bundle_dir, policy, seed, counts,
                              env=self.env_for(policy))

    def close(self) -> None:
        if self.env is not None:
            self.env.close()
            self.env = None

    def __enter__(self) -> "PolicyRollouts":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ------------------------------------------------------------------------------- one method
def simulate(scene: Scene, method: str, rollouts: Iterable[int], seed: int = 0,
             bundle_dir: str | Path | None = None,
             action_counts: dict[str, int] | None = None,
             deterministic: bool = False, noise_scale: float | None = None
             ) -> ScenarioRollouts:
    """Rollouts ``rollouts`` (indices) of one method on one scene, in this process.

    SUMO methods run one simulation after another here; the runner batches them in fresh
    worker processes (:func:`magail_sumo.evaluation.runner.run_batches`). Rollout ``r`` runs
    the policy ``make_policy(method, rollout_seed(seed, r), deterministic, noise_scale)``
    builds (one policy and one env for all, :class:`PolicyRollouts`).

    :param action_counts: a policy's fixed-up actions (the env's ``action_counts``: missing,
        unknown, non-finite, clipped) are added to it; they are also logged once.
    """
    ids = sim_agent_ids(scene)
    idx = list(rollouts)
    if method == "logreplay":
        return log_replay(scene, len(idx), N_STEPS)
    seeds = [rollout_seed(seed, r) for r in idx]
    counts: dict[str, int] = {}
    if method == "constvel":
        runs = [constant_velocity(scene, ids) for _ in seeds]
    elif not seeds:
        runs = []
    elif bundle_dir is None:
        raise EvaluationError(f"scenario {printable(scene.scenario_id)}: method {method} "
                              "needs a converted SUMO bundle")
    elif method == "sumo":
        runs = sumo_rollouts(scene, Path(bundle_dir), seeds, ids, N_STEPS)
    else:
        # lazy: baseline batches run in worker processes that import no torch
        from magail_sumo.policies import make_policy

        make = lambda s: make_policy(method, s, deterministic, noise_scale)  # noqa: E731
        policy = make(seeds[0])
        if batched(policy):  # every rollout at once (one env world per rollout)
            runs = batched_rollouts(scene, Path(bundle_dir), policy, seeds, counts)
        else:
            with PolicyRollouts(scene, bundle_dir, make) as pr:
                pr.policy = policy
                runs = [pr.run(s, counts) for s in seeds]

    fixed = action_summary(counts)
    if fixed:  # once per batch, in the run log
        log(f"warning: scenario {printable(scene.scenario_id)}: method {method} rollout(s) "
            f"{span(tuple(idx))}: {fixed}")
    if action_counts is not None:
        for k, v in counts.items():
            action_counts[k] = action_counts.get(k, 0) + int(v)
    xs, ys, yaws = ([run[k] for run in runs] for k in range(3))
    return as_rollouts(scene, ids, xs, ys, yaws)


# ------------------------------------------------------------------------------ worker batches
@dataclass(frozen=True)
class Batch:
    """Work for one worker process: some rollouts of one method on one scene.

    :param spec: method name or policy spec (see :func:`make_policy`).
    :param deterministic: a checkpoint policy acts deterministically (see :func:`make_policy`).
    :param noise_scale: its sampling noise's scale (None: the policy's own; see
        :func:`make_policy`).
    :param scene: the parsed scene (the worker reads ``scene_file`` when None).
    """

    scene_file: str
    scenario_id: str
    bundle_dir: str
    spec: str
    rollouts: tuple[int, ...]
    seed: int
    deterministic: bool = False
    noise_scale: float | None = None
    scene: Scene | None = field(default=None, compare=False, repr=False)


def run_batches_in_turn(batches: tuple[Batch, ...]) -> list[tuple]:
    """Worker entry point for several batches in one process (a policy's batches of several
    scenes: the process start and the policy's imports are paid once): per batch, in order,
    ``("ok", batch, rollouts, counts)`` or, for a :class:`~magail_sumo.errors.MagailSumoError`
    (a reported bad input), ``("error", batch, one-line reason)``; any other failure fails
    the whole call (the runner then retries the batches one per process)."""
    out: list[tuple] = []
    for b in batches:
        try:
            _, ro, counts = run_batch(b)
            out.append(("ok", replace(b, scene=None), ro, counts))
        except MagailSumoError as exc:
            out.append(("error", replace(b, scene=None), " ".join(str(exc).split())))
    return out


def run_batch(batch: Batch) -> tuple[Batch, ScenarioRollouts, dict[str, int]]:
    """Worker entry point (module level, picklable): the batch, its rollouts and the policy's
    fixed-up action counts."""
    scene = batch.scene if batch.scene is not None else \
        find_scene(batch.scene_file, batch.scenario_id)
    counts: dict[str, int] = {}
    ro = simulate(scene, batch.spec, batch.rollouts, batch.seed, batch.bundle_dir, counts,
                  batch.deterministic, batch.noise_scale)
    return replace(batch, scene=None), ro, counts
