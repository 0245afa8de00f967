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

import os
from collections import Counter
from pathlib import Path
from typing import Any, Iterable, Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn

from converters import iter_scenes
from converters.scene_files import RecordRef
from converters.sumo.bundle import bundle_folder, complete_bundle
from converters.sumo.scenario import ensure_bundle
from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import NameRegistry, printable
from magail_sumo.sensors.observation import observation_bounds
from magail_sumo.sim.dynamics import ACTION_SIZE

from .config import SCENE_CACHE, EnvConfig
# the worker side lives in .slot_worker (no torch or SB3 in the workers); its names stay
# importable from here
from .slot_worker import (PoolSpec, SceneSpec, SlotWorker, VecEnvWorkerError,  # noqa: F401
                          episode_rng, load_spec_scene, make_worker, max_concurrent_agents)
from .scene_pool import ScenePoolError, shard_pool
from .transport import WorkerFailed, WorkerLost, backend_class

SEED_STRIDE = 100_003
#: per-step cost of a scene worker in units of one agent's cost (SUMO step, log replay, sensor
#: set-up: about 1 ms of fixed work per step against about 0.1 ms per agent, measured on the
#: bundled scenes); used to balance workers over cores
WORKER_FIXED_COST = 10.0


def place_workers(loads: Sequence[float], cores: Sequence[int]) -> list[set[int]]:
    """CPU set of each worker: every worker pinned to one core, heaviest first onto the least
    loaded core (greedy longest-processing-time); with no more workers than cores, one core each.

    :param loads: relative per-step cost of each worker. :param cores: usable core ids.
    """
    cores = sorted(cores)
    if not cores:
        return [set() for _ in loads]
    total = {c: 0.0 for c in cores}
    out: list[set[int]] = [set() for _ in loads]
    for k in sorted(range(len(loads)), key=lambda i: (-loads[i], i)):
        c = min(cores, key=lambda c: (total[c], c))
        total[c] += loads[k]
        out[k] = {c}
    return out


class WorkerStartError(VecEnvWorkerError):
    """A scene worker could not start (:attr:`worker`: its index)."""

    def __init__(self, message: str, worker: int) -> None:
        super().__init__(message)
        self.worker = worker



# ---------------------------------------------------------------------------------- parent side
class MultiSceneVecEnv(VecEnv):
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
    :param backend_options: its options (Ray: ``address``, ``num_cpus``).
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
        self.timeout_s = timeout_s
        #: seconds a (re)started worker gets to start and replay its episode: at least a minute,
        #: as starting a process or actor, importing and building the scene take a while
        self.start_timeout_s = max(timeout_s, 60.0)
        self.backend = backend
        self.max_restarts = max_restarts
        self.log = log or (lambda msg: None)
        self._handle_cls = backend_class(backend)
        self._backend_opts = dict(backend_options or {}, start_method=start_method)
        if hasattr(self._handle_cls, "prepare"):
            self._handle_cls.prepare(self._backend_opts, len(self.specs))
        self.closed = False
        self.restarts = 0  #: workers replaced so far
        #: scenes skipped so far, (scene, reason) each, and those not yet taken by the trainer
        self.skipped: list[tuple[str, str]] = []
        self.new_skipped: list[tuple[str, str]] = []
        self._handles = []
        self._slots_asked = None if slots is None else list(slots)
        try:
            for k in range(len(self.specs)):
                self._handles.append(self._new_handle(k))
            hello = []
            for k in range(len(self.specs)):
                try:
                    hello.append(self._recv(k))
                except VecEnvWorkerError as exc:
                    raise WorkerStartError(str(exc), k) from None
        except BaseException:
            self._kill_all()
            raise
        self.slots = [h["slots"] for h in hello]
        #: where each worker runs: (host, pid)
        self.worker_hosts = [(h["host"], h["pid"]) for h in hello]
        #: CPU set of each worker (empty: not pinned)
        self.worker_cpus: list[set[int]] = [set() for _ in self.specs]
        self.pin_workers = pin_workers and backend == "process" and \
            hasattr(os, "sched_setaffinity")
        if self.pin_workers:
            self.worker_cpus = place_workers([WORKER_FIXED_COST + n for n in self.slots],
                                             os.sched_getaffinity(0))
            for k in range(len(self.specs)):
                self._pin(k)
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

    # ------------------------------------------------------------------ workers
    def _new_handle(self, k: int):
        spec = self.specs[k]
        slots = None if self._slots_asked is None else self._slots_asked[k]
        if hasattr(self, "slots"):  # a replacement keeps the layout
            slots = self.slots[k]
        h = self._handle_cls(f"scene {spec.name}", make_worker,
                             (spec, self.config, self.seed_base + SEED_STRIDE * k, slots),
                             self._backend_opts)
        h.start()
        return h

    def _pin(self, k: int) -> None:
        try:
            os.sched_setaffinity(self._handles[k].pid, self.worker_cpus[k])
        except (OSError, TypeError):  # gone (reported by the next answer) or denied
            pass

    @property
    def _procs(self) -> list:
        """The worker processes (process backend)."""
        return [getattr(h, "proc", None) for h in self._handles]

    def _recv(self, k: int) -> Any:
        try:
            return self._handles[k].recv(self.timeout_s)
        except (WorkerLost, WorkerFailed) as exc:
            self._kill_all()
            raise VecEnvWorkerError(str(exc)) from None

    def _restart(self, k: int) -> None:
        """Kill worker ``k`` and start a fresh one with the same source, seed and slots."""
        self._handles[k].kill()
        self._handles[k] = self._new_handle(k)
        self._handles[k].recv(self.start_timeout_s)  # hello
        if self.pin_workers:
            self._pin(k)

    def _replace(self, k: int, reason: str) -> None:
        """Start a fresh worker ``k`` in the state of the lost one (same seed; the current
        episode replayed)."""
        self._restart(k)
        acts = self._ep_actions[k]
        self._handles[k].send("restore", (self._episode[k], acts), self.start_timeout_s)
        self._handles[k].recv(self.start_timeout_s)
        self.restarts += 1
        self.log(f"worker {k} ({self.specs[k].name}) lost: {reason.splitlines()[0]}; replaced "
                 f"on {self._handles[k].node or 'local'}, episode {self._episode[k]} replayed "
                 f"({len(acts)} steps)")

    def _exchange(self, cmd: str, args: Sequence[Any], workers: Sequence[int] | None = None
                  ) -> list[Any]:
        """Send ``(cmd, args[i])`` to each worker and collect the answers; a lost worker is
        replaced (up to :attr:`max_restarts` times in a row) and asked again."""
        return self._gather(cmd, args, workers, self._send(cmd, args, workers))

    def _send(self, cmd: str, args: Sequence[Any], workers: Sequence[int] | None = None
              ) -> dict[int, str]:
        """The sending half of :meth:`_exchange`: the workers lost on the way (reason each)."""
        if self.closed:
            raise VecEnvWorkerError("the vector env is closed")
        ks = list(range(len(self.specs))) if workers is None else list(workers)
        lost: dict[int, str] = {}
        for k, arg in zip(ks, args):
            try:
                self._handles[k].send(cmd, arg, self.timeout_s)
            except WorkerLost as exc:
                lost[k] = str(exc)
        return lost

    def _gather(self, cmd: str, args: Sequence[Any], workers: Sequence[int] | None,
                lost: dict[int, str]) -> list[Any]:
        """The receiving half of :meth:`_exchange` (``lost``: from :meth:`_send`)."""
        ks = list(range(len(self.specs))) if workers is None else list(workers)
        out = []
        for k, arg in zip(ks, args):
            tries = 0
            while True:
                try:
                    if k not in lost:
                        out.append(self._handles[k].recv(self.timeout_s))
                        break
                    reason = lost.pop(k)
                except WorkerLost as exc:
                    reason = str(exc)
                except WorkerFailed as exc:
                    self._kill_all()
                    raise VecEnvWorkerError(str(exc)) from None
                tries += 1
                if tries > self.max_restarts:
                    self._kill_all()
                    raise VecEnvWorkerError(reason + (f" ({self.max_restarts} replacement(s) "
                                                      "failed too)" if self.max_restarts else ""))
                try:
                    if cmd in ("reset", "restore"):  # the request itself sets the state
                        self._restart(k)
                        self.restarts += 1
                        self.log(f"worker {k} ({self.specs[k].name}) lost: "
                                 f"{reason.splitlines()[0]}; replaced")
                    else:
                        self._replace(k, reason)
                    self._handles[k].send(cmd, arg, self.timeout_s)
                except WorkerLost as exc:
                    lost[k] = str(exc)
                except WorkerFailed as exc:
                    self._kill_all()
                    raise VecEnvWorkerError(str(exc)) from None
        return out

    def _kill_all(self) -> None:
        for h in self._handles:
            try:
                h.kill()
            except Exception:  # noqa: BLE001 - best effort
                pass
        self.closed = True

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


def scene_specs(scene_files: Iterable[str | Path], networks: str | Path,
                convert_missing: bool = True, errors: list[str] | None = None,
                time_budget_s: float | None = 600.0) -> list[SceneSpec]:
    """A :class:`SceneSpec` per scene of ``scene_files`` with its bundle under ``networks``
    (``networks/<name>/``, ``name`` = :func:`magail_sumo.outputs.safe_name` of the scenario
    id), converting the scenes that have none yet (baseline run skipped, ``time_budget_s``
    seconds each at most) into ``networks`` once it is claimed
    (:func:`converters.sumo.scenario.ensure_bundle`). Two scenes whose ids map to one name
    are refused (:class:`~magail_sumo.outputs.OutputError`).

    :param errors: when given, a scene (or file) that cannot be used is appended here as a
        one-line reason and left out, instead of raising :class:`MagailSumoError`.
    """
    networks = Path(networks)
    names = NameRegistry()
    out = []

    def fail(msg: str) -> None:
        if errors is None:
            raise MagailSumoError(msg)
        errors.append(msg)

    for f in scene_files:
        try:
            for index, scene in enumerate(iter_scenes(f)):
                sid = scene.scenario_id
                names.name(sid)  # two ids of one name: refused
                if not convert_missing:
                    folder = complete_bundle(networks, sid)
                    if folder is None:
                        fail(f"{bundle_folder(networks, sid)}: no converted bundle for scene "
                             f"{printable(sid)}")
                        continue
                else:
                    try:
                        folder = ensure_bundle(scene, networks, RecordRef(str(f), index),
                                               time_budget_s, claim=True)
                    except MagailSumoError as exc:
                        fail(f"{f}: {exc}")
                        continue
                out.append(SceneSpec(str(f), str(folder), sid))
        except Exception as exc:  # noqa: BLE001 - an unreadable file
            if errors is None:
                raise
            errors.append(printable(f"{f}: " + (str(exc) if isinstance(exc, MagailSumoError)
                                                 else f"{type(exc).__name__}: {exc}"), 400))
    return out


def pool_vec_env(refs: Sequence, networks: str | Path, workers: int,
                 config: EnvConfig | None = None, seed: int = 0, *, cache: int = SCENE_CACHE,
                 convert_budget_s: float | None = 90.0, city=None, log=None, **kwargs
                 ) -> MultiSceneVecEnv:
    """A :class:`MultiSceneVecEnv` over a scene pool: ``refs``
    (:func:`~magail_sumo.env.scene_pool.resolve_pool`) sharded over ``workers`` workers
    (:func:`~magail_sumo.env.scene_pool.shard_pool`), bundles converted on demand into
    ``networks``; ``city`` configures the pool's city scenarios
    (:class:`~magail_sumo.env.city_env.CityEnvConfig`). A worker none of whose scenes can be used at start-up has its scenes
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
        specs = [PoolSpec(tuple(sh), str(networks), cache, convert_budget_s, city)
                 for sh in shards]
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
