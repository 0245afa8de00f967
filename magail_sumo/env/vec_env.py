"""Stable-Baselines3 ``VecEnv`` over scene workers: agents as vector slots.

A scene worker (:class:`SlotWorker`) runs one SUMO at a time (libsumo runs one simulation per
process) and plays either one scene (:class:`SceneSpec`) or a shard of a scene pool
(:class:`PoolSpec`, :mod:`magail_sumo.env.scene_pool`: a new scene, recorded or a city, at
each episode). Workers run on a backend (:mod:`magail_sumo.env.transport`: local processes
started with ``spawn`` over pipes, or Ray actors); every answer (and the write of every large
request) is awaited with a timeout, so a worker that dies, hangs or is stopped never hangs the
trainer: it is replaced (``max_restarts``; its episode replayed, see Determinism) or the env
raises :class:`VecEnvWorkerError` naming the scene.

Slots: worker ``k`` owns ``slots[k]`` consecutive slots, as many as its agents can ever be
alive at once (from the recorded track lifetimes; a city's ``max_agents``). An agent joining
takes the lowest free slot of its worker and keeps it until it leaves; then the slot is free
until another agent joins.
``infos[i]["slot_active"]`` (and :attr:`MultiSceneVecEnv.slot_active`) says whether slot ``i``
holds an agent; the observation of a free slot is zeros and its action is ignored. Learning
must drop free slot-steps (see :class:`magail_sumo.training.gail.ppo.MaskedRolloutBuffer`):
they are not transitions. ``dones[i]`` is True when the slot's agent left (with
``infos[i]["terminal_observation"]``, ``"TimeLimit.truncated"`` when it was truncated, not
terminated, and ``"reason"``) and also when a free slot is given to a new agent, so GAE never
runs from one agent into another. When a worker's scene has no agents left it is reset (next
episode, next scene of its shard) inside the same step. :attr:`MultiSceneVecEnv.slot_pos` is
each slot's pose for the current observation (x, y in m, yaw in rad; scene frame; the agent's
bicycle state, zeros for a free slot), sent by the workers as one small (slots, 3) float32
array per step.

Determinism: episode ``e`` of worker ``k`` is reset with seed ``seed + 100_003·k + e``; its
scene is a pure function of the worker seed and ``e`` (:class:`~magail_sumo.env.scene_pool.
PoolCursor`), and with ``EnvConfig.start_window: random`` so is its start step
(:func:`episode_rng`). The env logs each worker's episode index and the actions since that
episode's reset, so :meth:`MultiSceneVecEnv.get_state` / :meth:`~MultiSceneVecEnv.set_state`
restore the exact simulation state in fresh workers by replaying them (exact training resume),
and a replaced worker continues exactly where the lost one was.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any, Callable, Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn

from magail_sumo.sensors.observation import observation_bounds
from magail_sumo.sim.dynamics import ACTION_SIZE

from .config import SCENE_CACHE, EnvConfig
# the worker side lives in .slot_worker (no torch or SB3 in the workers); its names stay
# importable from here
from .slot_worker import (PoolSpec, SceneSpec, SlotWorker, VecEnvWorkerError,  # noqa: F401
                          episode_rng, load_spec_scene, make_worker, max_concurrent_agents)
from .scene_pool import ScenePoolError, shard_pool
from .supervision import (SEED_STRIDE, WORKER_FIXED_COST, WorkerStartError,  # noqa: F401
                          WorkerSupervisor, place_workers)

# ---------------------------------------------------------------------------------- parent side
class MultiSceneVecEnv(WorkerSupervisor, VecEnv):
    """Agents of several scene workers as SB3 vector slots (module doc).

    :param scenes: one source per worker: a :class:`SceneSpec` (one scene, explicit bundle) or
        a :class:`PoolSpec` (a shard of a scene pool).
    :param config: env configuration shared by all scenes.
    :param seed: base seed of the episode seeds.
    :param slots: slots per worker (None: from its scene(s)).
    :param timeout_s: seconds to wait for any worker answer before giving up on it.
    :param start_method: ``"spawn"`` or ``"forkserver"`` (process backend).
    :param pin_workers: pin each worker process to one core, balancing the workers' per-step
        cost (:func:`place_workers`, cost = fixed + slots); the trainer process stays unpinned.
        Meant for a machine dedicated to one run: concurrent runs pinning their workers would
        stack them on the same cores. Linux and the process backend only, ignored elsewhere.
    :param backend: worker backend (:data:`magail_sumo.env.transport.BACKENDS`).
    :param backend_options: its options (Ray: ``address``, ``num_cpus``, ``node_ip``).
    :param max_restarts: how many times in a row a worker that dies or stops answering is
        replaced (its episode replayed from its seed and logged actions, so the rollout goes on
        exactly as it would have) before the env gives up with :class:`VecEnvWorkerError`;
        0: give up at once.
    :param log: where replacements and skipped scenes are reported (one line each).
    """

    def __init__(self, scenes: Sequence[SceneSpec | PoolSpec], config: EnvConfig | None = None,
                 seed: int = 0, slots: Sequence[int] | None = None, timeout_s: float = 120.0,
                 start_method: str = "spawn", pin_workers: bool = False,
                 backend: str = "process", backend_options: dict | None = None,
                 max_restarts: int = 0, log=None) -> None:
        if not scenes:
            raise ValueError("MultiSceneVecEnv needs at least one scene")

        self.specs = list(scenes)
        self.config = config or EnvConfig()
        self.seed_base = seed
        self.log = log or (lambda msg: None)
        #: scenes skipped so far, (scene, reason) each, and those not yet taken by the trainer
        self.skipped: list[tuple[str, str]] = []
        self.new_skipped: list[tuple[str, str]] = []
        hello = self._start_workers(slots, timeout_s, start_method, pin_workers, backend,
                                    backend_options, max_restarts)
        self.possible_agents = [h["possible_agents"] for h in hello]
        low, high = observation_bounds(self.config.observation)
        self.obs_dim = int(low.shape[0])
        offsets = np.concatenate([[0], np.cumsum(self.slots)])
        self.scene_slices = [slice(int(a), int(b)) for a, b in zip(offsets[:-1], offsets[1:])]
        n = int(offsets[-1])
        #: (num_envs,) worker ("scene group") index of each slot
        self.slot_scene = np.repeat(np.arange(len(self.specs)), self.slots)
        self._slot_scene_list: list[int] = self.slot_scene.tolist()
        #: (num_envs,) slot holds an agent (for the current observation)
        self.slot_active = np.zeros(n, bool)
        #: the mask of the observation before the last step (what the last actions acted on)
        self.prev_slot_active = np.zeros(n, bool)
        #: (num_envs, 3) float32 pose of each slot's agent for the current observation: x, y (m)
        #: and yaw (rad), scene frame (zeros for a free slot)
        self.slot_pos = np.zeros((n, 3), np.float32)
        #: the poses of the observation before the last step (those of s of the last transition)
        self.prev_slot_pos = np.zeros((n, 3), np.float32)
        self.agent_steps = 0  #: agent-steps stepped so far (active slots only)
        self.steps = 0  #: vector steps so far (every slot of every scene at once)
        #: called with :attr:`steps` after each vector step (a trainer's progress), or None
        self.on_step: Callable[[int], None] | None = None
        self.episodes = 0  #: scene episodes finished so far
        #: agent-steps whose acceleration the gap guard lowered so far (``env.guard``)
        self.guarded = 0
        #: agent episodes ended so far, by reason (``collision``, ``off_road``, ``horizon``…)
        self.end_reasons: Counter[str] = Counter()
        #: scenario id each worker plays now
        self.worker_scene: list[str] = ["" for _ in self.specs]
        # per worker: its episode index and the actions since that episode's reset (the state
        # get_state gives and a replaced worker replays)
        self._episode = [0] * len(self.specs)
        self._ep_actions: list[list[np.ndarray]] = [[] for _ in self.specs]
        #: the step sent by step_async and not yet gathered: its per-worker actions and the
        #: workers lost while sending it (None: no step in flight)
        self._step_args: list[np.ndarray] = []
        self._step_lost: dict[int, str] | None = None
        super().__init__(n, spaces.Box(low, high, dtype=np.float32),
                         spaces.Box(-1.0, 1.0, (ACTION_SIZE,), np.float32))

    def _replay_state(self, k: int) -> tuple[int, list[np.ndarray]]:
        return self._episode[k], self._ep_actions[k]

    # ------------------------------------------------------------------ VecEnv API
    def _collect(self, packets: list[dict], step: bool) -> tuple:
        obs = np.concatenate([p["obs"] for p in packets])
        dones = np.concatenate([p["dones"] for p in packets])
        active = np.concatenate([p["active"] for p in packets])
        pos = np.concatenate([p["pos"] for p in packets])
        infos: list[dict[str, Any]] = [{"slot_active": a, "scene": s}
                                       for a, s in zip(active.tolist(), self._slot_scene_list)]
        for k, p in enumerate(packets):
            base = self.scene_slices[k].start
            for j, info in p["infos"].items():
                infos[base + j].update(info)
            if step:
                self.agent_steps += p["agent_steps"]
                self.episodes += p["episodes"]
                self.guarded += p["guarded"]
                self.end_reasons.update(str(i["reason"]) for i in p["infos"].values()
                                        if i.get("reason"))
            self._episode[k] = p["episode"]
            self.worker_scene[k] = p["scenario_id"]
            for what, reason in p["skipped"]:
                self.skipped.append((what, reason))
                self.new_skipped.append((what, reason))
                self.log(f"scene skipped: {what}: {reason}")
        self.prev_slot_active = self.slot_active
        self.slot_active = active
        self.prev_slot_pos = self.slot_pos
        self.slot_pos = pos
        return obs, dones, infos

    def reset(self) -> np.ndarray:
        packets = self._exchange("reset", [None] * len(self.specs))
        self._ep_actions = [[] for _ in self.specs]
        obs, _, infos = self._collect(packets, step=False)
        self.prev_slot_active = np.zeros(self.num_envs, bool)
        self.prev_slot_pos = np.zeros((self.num_envs, 3), np.float32)
        self.reset_infos = infos
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        """Send the actions: the workers step while the caller goes on until :meth:`step_wait`
        (e.g. the deferred imitation rewards of earlier steps are computed meanwhile)."""
        actions = np.asarray(actions, np.float32).reshape(self.num_envs, 2)
        self._step_args = [actions[s] for s in self.scene_slices]
        self._step_lost = self._send("step", self._step_args)

    def step_wait(self) -> VecEnvStepReturn:
        acts, lost = self._step_args, self._step_lost
        self._step_lost = None
        if lost is None:
            raise RuntimeError("step_wait without step_async")
        packets = self._gather("step", acts, None, lost)
        for k, p in enumerate(packets):
            if p["episodes"]:
                self._ep_actions[k] = []
            else:
                self._ep_actions[k].append(acts[k].copy())
        obs, dones, infos = self._collect(packets, step=True)
        self.steps += 1
        if self.on_step is not None:
            self.on_step(self.steps)
        return obs, np.zeros(self.num_envs, np.float32), dones, infos

    def get_state(self) -> list[tuple[int, list[np.ndarray]]]:
        """Per worker (episode index, actions since its reset): enough to rebuild the state."""
        if self.closed:
            raise VecEnvWorkerError("the vector env is closed")
        return [(int(e), [a.copy() for a in acts])
                for e, acts in zip(self._episode, self._ep_actions)]

    def set_state(self, state: Sequence[tuple[int, list[np.ndarray]]]) -> np.ndarray:
        """Rebuild the state :meth:`get_state` gave (replaying actions); the observation."""
        if len(state) != len(self.specs):
            raise ValueError(f"state has {len(state)} scenes, the env {len(self.specs)}")
        packets = self._exchange("restore", list(state))
        self._ep_actions = [[np.asarray(a, np.float32).reshape(self.slots[k], 2)
                             for a in acts] for k, (_, acts) in enumerate(state)]
        obs, _, infos = self._collect(packets, step=False)
        self.prev_slot_active = np.zeros(self.num_envs, bool)
        self.prev_slot_pos = np.zeros((self.num_envs, 3), np.float32)
        self.reset_infos = infos
        return obs

    def close(self) -> None:
        if self.closed:
            return
        for h in self._handles:
            try:
                h.close()
            except Exception:  # noqa: BLE001 - best effort
                pass
        self._kill_all()

    def _scenes_of(self, indices: VecEnvIndices) -> list[int]:
        return sorted({int(self.slot_scene[i]) for i in self._get_indices(indices)})

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """Attribute of the scene env of each slot of ``indices``."""
        scenes = self._scenes_of(indices)
        got = dict(zip(scenes, self._exchange("getattr", [attr_name] * len(scenes), scenes)))
        return [got[int(self.slot_scene[i])] for i in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        raise NotImplementedError("scene envs are configured through EnvConfig")

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None,
                   **method_kwargs) -> list[Any]:
        scenes = self._scenes_of(indices)
        got = dict(zip(scenes, self._exchange(
            "call", [(method_name, method_args, method_kwargs)] * len(scenes), scenes)))
        return [got[int(self.slot_scene[i])] for i in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None
                       ) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def seed(self, seed: int | None = None) -> Sequence[int | None]:
        return [None] * self.num_envs

    def __del__(self) -> None:  # pragma: no cover - best effort
        try:
            if not self.closed:
                self._kill_all()
        except Exception:
            pass


def pool_vec_env(refs: Sequence, networks: str | Path, workers: int,
                 config: EnvConfig | None = None, seed: int = 0, *, cache: int = SCENE_CACHE,
                 convert_budget_s: float | None = 90.0, city=None, log=None,
                 scenes_per_env: int = 1, **kwargs) -> MultiSceneVecEnv:
    """A :class:`MultiSceneVecEnv` over a scene pool: ``refs``
    (:func:`~magail_sumo.env.scene_pool.resolve_pool`) sharded over ``workers`` workers
    (:func:`~magail_sumo.env.scene_pool.shard_pool`), bundles converted on demand into
    ``networks``; ``city`` configures the pool's city scenarios
    (:class:`~magail_sumo.env.city_env.CityEnvConfig`); ``scenes_per_env`` > 1: each worker
    steps that many recorded scenes as one tiled env (:mod:`~magail_sumo.env.tile_pool`). A
    worker none of whose scenes can be used at start-up has its scenes
    reported as skipped (``venv.skipped``) and the pool is sharded again without them.
    ``kwargs`` go to :class:`MultiSceneVecEnv` (timeout, backend, restarts, ...)."""
    refs = list(refs)
    skipped: list[tuple[str, str]] = []
    log = log or (lambda msg: None)
    while True:
        if not refs:
            raise ScenePoolError("no scene of the pool can be used" + (
                f"; first: {skipped[0][0]}: {skipped[0][1]}" if skipped else ""))
        shards = shard_pool(refs, workers)
        specs = [PoolSpec(tuple(sh), str(networks), cache, convert_budget_s, city,
                          scenes_per_env) for sh in shards]
        try:
            venv = MultiSceneVecEnv(specs, config, seed, log=log, **kwargs)
        except WorkerStartError as exc:
            if "ScenePoolError" not in str(exc):
                raise
            bad = set(shards[exc.worker])
            reason = str(exc).splitlines()[0]
            reason = reason[reason.find("ScenePoolError"):]
            for r in shards[exc.worker]:
                skipped.append((str(r), reason))
                log(f"scene skipped: {r}: {reason}")
            refs = [r for r in refs if r not in bad]
            continue
        venv.skipped[:0] = skipped
        venv.new_skipped[:0] = skipped
        return venv
