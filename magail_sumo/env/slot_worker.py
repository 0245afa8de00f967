"""The scene worker: one SUMO at a time, its scene(s) and its agents' vector slots.

A :class:`SlotWorker` runs inside a worker process or Ray actor (started by
:class:`~magail_sumo.env.vec_env.MultiSceneVecEnv` through :mod:`magail_sumo.env.transport`,
built by :func:`make_worker`). It plays either one scene (:class:`SceneSpec`) or a shard of a
scene pool (:class:`PoolSpec`, :mod:`magail_sumo.env.scene_pool`) and answers the trainer's
``step`` / ``reset`` / ``restore`` requests with one packet of arrays per worker (slots,
determinism and the packet's fields: :mod:`magail_sumo.env.vec_env`).

This module imports neither torch nor Stable-Baselines3 (nor does anything it imports at
module level): a worker process holds SUMO, the scene and the sensors only, about 0.5 GiB less
than the learner's imports (README "Scene pools and workers"; measured by
``benchmarks/pool_memory.py``). ``tests/test_vec_env.py`` checks that importing it leaves them
out.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from converters import find_scene
from magail_sumo.errors import MagailSumoError
from magail_sumo.sensors.observation import observation_bounds

from .config import SCENE_CACHE, EnvConfig
from .driving_env import SumoDrivingEnv
from .scene_pool import PoolCursor, is_city, max_concurrent_agents
from .tile_pool import TileCursor

__all__ = ["PoolSpec", "SceneSpec", "SlotWorker", "VecEnvWorkerError", "episode_rng",
           "load_spec_scene", "make_worker", "max_concurrent_agents", "runs_sumo"]


class VecEnvWorkerError(MagailSumoError):
    """A scene worker process died, failed, or did not answer in time."""


@dataclass(frozen=True)
class SceneSpec:
    """One scene for a worker: the scene file, its converted bundle folder, and which scene of
    the file (``scenario_id``; None: the first)."""

    scene_file: str
    bundle: str
    scenario_id: str | None = None

    @property
    def name(self) -> str:
        return self.scenario_id or Path(self.scene_file).stem


def load_spec_scene(spec: SceneSpec):
    """The :class:`~magail_sumo.scene.Scene` a spec names (:func:`converters.find_scene`)."""
    return find_scene(spec.scene_file, spec.scenario_id)


def episode_rng(seed: int, episode: int) -> np.random.Generator:
    """The generator drawing episode ``episode``'s start window of a worker seeded ``seed``."""
    return np.random.default_rng(np.random.SeedSequence([seed % (1 << 64), episode]))


@dataclass(frozen=True)
class PoolSpec:
    """A worker's shard of a scene pool (:mod:`magail_sumo.env.scene_pool`): its records, the
    bundles folder (missing bundles are converted there on demand), how many scene envs it
    keeps, and the time budget of one conversion."""

    refs: tuple
    networks: str
    cache: int = SCENE_CACHE
    convert_budget_s: float | None = 600.0
    #: :class:`~magail_sumo.env.city_env.CityEnvConfig` of the pool's city scenarios
    city: Any = None
    #: recorded scenes stepped as one tiled env (:mod:`magail_sumo.env.tile_pool`; 1: one)
    scenes_per_env: int = 1

    @property
    def name(self) -> str:
        first = str(self.refs[0]) if self.refs else "(empty)"
        return first if len(self.refs) == 1 else f"{first} +{len(self.refs) - 1} scenes"


def _scenario_id(env) -> str:
    """The id of a scene env's scene, or a city env's scenario name."""
    sid = getattr(env, "scenario_id", None)
    return sid if sid is not None else env.scene.scenario_id


class _FixedScene:
    """The :class:`~magail_sumo.env.scene_pool.PoolCursor` interface over one
    :class:`SceneSpec` (an explicit bundle folder)."""

    def __init__(self, spec: SceneSpec, make_env) -> None:
        self._env = make_env(load_spec_scene(spec), spec.bundle)
        self.new_failures: list = []

    def env_for(self, episode: int):
        return 0, self._env

    def scan(self) -> int:
        return max_concurrent_agents(self._env)

    def close(self) -> None:
        self._env.close()


class SlotWorker:
    """The env of a worker's scene(s) with its slot bookkeeping (runs in the worker).

    A recorded-scene episode runs on the env's array API (``reset_arrays`` / ``step_arrays``
    with :meth:`~magail_sumo.env.driving_env.SumoDrivingEnv.run_on_arrays`, slots kept as
    fleet rows: no dict or info per agent); a city episode, or one recording FCD, on the
    PettingZoo dicts. Both give the same packets (``tests/test_slot_worker.py`` checks every
    real scene in ``data/``).

    :param source: a :class:`SceneSpec` (one scene) or a :class:`PoolSpec` (a shard).
    :param slots: slot count (None: from the scene(s), see the module docs).
    """

    def __init__(self, source: SceneSpec | PoolSpec, config: EnvConfig, seed: int,
                 slots: int | None) -> None:
        def make_env(scene, bundle):
            return SumoDrivingEnv(scene, bundle, config)

        if isinstance(source, PoolSpec):
            self.cursor = PoolCursor(source.refs, source.networks, seed, make_env, config,
                                     source.cache, source.convert_budget_s, source.city)
            if source.scenes_per_env > 1:  # several recorded scenes as one tiled env
                self.cursor = TileCursor(self.cursor, source.scenes_per_env, config)
        else:
            self.cursor = _FixedScene(source, make_env)
        self.config = config
        self.slots = slots or self.cursor.scan()
        if isinstance(self.cursor, PoolCursor) and len(self.cursor.refs) > 1:
            self.cursor.slots = self.slots  # a scene needing more is skipped when played

        self.dim = int(observation_bounds(config.observation)[0].shape[0])
        self.base_seed = seed
        self.episode = -1
        self.env = self.cursor.env_for(0)[1]
        self.names: list[str | None] = [None] * self.slots
        self.slot_of: dict[str, int] = {}  #: agent name -> its slot (the agents in slots)
        #: the episode runs on the env's array API (a recorded scene, no FCD): the slots are
        #: kept as fleet rows (:attr:`slot_row`, :attr:`row_slot`) instead of names
        self.arrays = False
        self.slot_row = np.full(self.slots, -1, np.int64)  #: fleet row of each slot (-1: free)
        self.row_slot = np.zeros(0, np.int64)  #: slot of each fleet row (-1: none)

    def hello(self) -> dict:
        import socket

        agents = list(self.env.possible_agents)
        return {"slots": self.slots, "dim": self.dim, "host": socket.gethostname(),
                "pid": os.getpid(), "possible_agents": agents if len(agents) <= 4096 else []}

    def handle(self, cmd: str, arg: Any) -> Any:
        if cmd == "step":
            return self.step(arg)
        if cmd == "reset":
            return self.reset()
        if cmd == "restore":
            return self.restore(*arg)
        if cmd == "call":
            name, args, kwargs = arg
            return getattr(self.env, name)(*args, **kwargs)
        if cmd == "getattr":
            return getattr(self.env, arg)
        raise ValueError(f"unknown command {cmd!r}")

    def _assign(self, obs: dict[str, np.ndarray], packet: dict) -> None:
        slot_of, names = self.slot_of, self.names
        for name in self.env.agents:
            if name in slot_of:
                continue
            try:
                k = names.index(None)
            except ValueError:
                raise VecEnvWorkerError(f"{_scenario_id(self.env)}: more than {self.slots} "
                                        "agents alive at once") from None
            names[k] = name
            slot_of[name] = k
            packet["dones"][k] = True  # slot re-assignment = episode start of the slot
        if slot_of:
            ks = np.fromiter(slot_of.values(), np.int64, len(slot_of))
            packet["obs"][ks] = np.stack([obs[n] for n in slot_of])
            st = self.env.agent_states()  # the live agents = the agents in slots
            ks = np.fromiter((slot_of[n] for n in st.names), np.int64, len(st.names))
            packet["pos"][ks] = np.stack([st.state.x, st.state.y, st.state.yaw], axis=1)

    def _packet(self) -> dict:
        return {"obs": np.zeros((self.slots, self.dim), np.float32),
                "pos": np.zeros((self.slots, 3), np.float32),
                "dones": np.zeros(self.slots, bool), "infos": {}, "episodes": 0,
                "agent_steps": 0, "guarded": 0, "skipped": []}

    def _active(self) -> np.ndarray:
        if self.arrays:
            return self.slot_row >= 0
        active = np.zeros(self.slots, bool)
        active[list(self.slot_of.values())] = True
        return active

    def _uses_arrays(self) -> bool:
        """Whether this episode runs on the env's array API: a recorded-scene env (a city
        env has none) recording no FCD (the dict API records its frames)."""
        return isinstance(self.env, SumoDrivingEnv) and self.config.fcd_dir is None

    def _assign_rows(self, obs: np.ndarray, live: np.ndarray, packet: dict) -> None:
        """:meth:`_assign` over fleet rows: each live row without a slot takes the lowest
        free one, in row order (the dict API's agent order); every slot's observation and
        pose from ``obs`` (the array step's buffer) and the fleet."""
        row_slot, slot_row = self.row_slot, self.slot_row
        new = np.flatnonzero(live & (row_slot < 0))
        if new.size:
            free = np.flatnonzero(slot_row < 0)
            if free.size < new.size:
                raise VecEnvWorkerError(f"{_scenario_id(self.env)}: more than {self.slots} "
                                        "agents alive at once")
            ks = free[:new.size]
            slot_row[ks] = new
            row_slot[new] = ks
            packet["dones"][ks] = True  # slot re-assignment = episode start of the slot
        ks = np.flatnonzero(slot_row >= 0)
        if ks.size:
            rows = slot_row[ks]
            f = self.env.fleet
            packet["obs"][ks] = obs[rows]
            packet["pos"][ks] = np.stack([f.x[rows], f.y[rows], f.yaw[rows]], axis=1)

    def _step_arrays(self, actions: np.ndarray, packet: dict) -> None:
        """:meth:`step` on the env's array API: the same packet, no dict per agent."""
        env, slot_row = self.env, self.slot_row
        ks = np.flatnonzero(slot_row >= 0)
        rows = slot_row[ks]
        full = np.zeros((self.row_slot.size, 2), np.float32)
        full[rows] = actions[ks]
        packet["agent_steps"] = int(ks.size)
        guarded = env.guarded
        out = env.step_arrays(full)
        packet["guarded"] = env.guarded - guarded
        gone = (out.terminated | out.truncated)[rows]
        if gone.any():
            ks_gone, rows_gone = ks[gone], rows[gone]
            names, events = env.fleet.names, env.events
            reasons = env.array_reasons(out, rows_gone)
            cut = (out.truncated & ~out.terminated)[rows_gone].tolist()
            flags = [(e, out.events[e][rows_gone].tolist()) for e in events]
            for i, (k, r) in enumerate(zip(ks_gone.tolist(), rows_gone.tolist())):
                packet["dones"][k] = True
                packet["infos"][k] = {
                    "terminal_observation": np.array(out.observations[r], np.float32),
                    "TimeLimit.truncated": cut[i], "reason": reasons[i], "agent": names[r],
                    "events": {e: col[i] for e, col in flags}}
            slot_row[ks_gone] = -1
            self.row_slot[rows_gone] = -1
        live = out.live
        if not live.any() and env.run_on_arrays().size:
            live = env.fleet.active[:live.size].copy()
        if not live.any():
            self._reset(packet)
            packet["episodes"] = 1
        else:
            self._assign_rows(out.observations, live, packet)

    def _reset(self, packet: dict) -> None:
        self.episode += 1
        self.names = [None] * self.slots
        self.slot_of = {}
        _, env = self.cursor.env_for(self.episode)
        if env is not self.env:
            self.env.close()
            self.env = env
        cfg = self.config
        options = None
        if cfg.start_window == "random" and hasattr(self.env, "scene"):  # not a city
            options = self.env.window_options(episode_rng(self.base_seed, self.episode))
        self.arrays = self._uses_arrays()
        self.slot_row[:] = -1
        if self.arrays:
            out = self.env.reset_arrays(seed=self.base_seed + self.episode, options=options)
            self.row_slot = np.full(out.live.size, -1, np.int64)
            self._assign_rows(out.observations, out.live, packet)
            return
        obs, _ = self.env.reset(seed=self.base_seed + self.episode, options=options)
        self._assign(obs, packet)

    def _finish(self, packet: dict) -> dict:
        packet["active"] = self._active()
        packet["episode"] = self.episode
        packet["scenario_id"] = _scenario_id(self.env)
        packet["skipped"] = [(s.what, s.reason) for s in self.cursor.new_failures]
        self.cursor.new_failures.clear()
        return packet

    def reset(self) -> dict:
        self.episode = -1
        packet = self._packet()
        self._reset(packet)
        packet["dones"][:] = False
        return self._finish(packet)

    def step(self, actions: np.ndarray) -> dict:
        actions = np.asarray(actions, np.float32).reshape(self.slots, 2)
        packet = self._packet()
        if self.arrays:
            self._step_arrays(actions, packet)
            return self._finish(packet)
        acts = {n: actions[k] for n, k in self.slot_of.items()}
        packet["agent_steps"] = len(acts)
        guarded = self.env.guarded
        obs, _, terms, truncs, infos = self.env.step(acts)
        packet["guarded"] = self.env.guarded - guarded  # before a reset zeroes it
        for name, k in list(self.slot_of.items()):
            if not (terms.get(name) or truncs.get(name)):
                continue
            info = infos[name]
            packet["dones"][k] = True
            packet["infos"][k] = {"terminal_observation": np.asarray(obs[name], np.float32),
                                  "TimeLimit.truncated": bool(truncs[name] and not terms[name]),
                                  "reason": info.get("reason"), "agent": name,
                                  "events": info.get("events", {})}
            self.names[k] = None
            del self.slot_of[name]
        if not self.env.agents:
            self._reset(packet)
            packet["episodes"] = 1
        else:
            self._assign(obs, packet)
        return self._finish(packet)

    def restore(self, episode: int, actions: Sequence[np.ndarray]) -> dict:
        """Reset to ``episode`` and replay ``actions`` (the actions since that episode's reset):
        the state the vector env logged (:meth:`MultiSceneVecEnv.get_state`)."""
        self.episode = episode - 1
        packet = self._packet()
        self._reset(packet)
        skipped = list(self.cursor.new_failures)
        for a in actions:
            packet = self.step(a)
        self.cursor.new_failures[:0] = skipped
        return self._finish(packet)

    def close(self) -> None:
        self.env.close()
        self.cursor.close()


def runs_sumo(source, config: EnvConfig) -> bool:
    """Whether a worker of ``source`` may run a SUMO simulation (libsumo runs one per process,
    so such a worker needs a process of its own): recorded scenes with SUMO background or the
    SUMO mirror, or a pool shard holding a city scenario."""
    if config.sumo_mirror or config.background != "log":
        return True
    return isinstance(source, PoolSpec) and any(is_city(r) for r in source.refs)


def make_worker(source, config: EnvConfig, seed: int, slots: int | None) -> SlotWorker:
    return SlotWorker(source, config, seed, slots)
