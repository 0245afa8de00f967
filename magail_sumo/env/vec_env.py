"""Stable-Baselines3 ``VecEnv`` over one or more scenes: agents as vector slots.

Each scene's :class:`~magail_sumo.env.driving_env.SumoDrivingEnv` lives in its own worker
process (libsumo runs one simulation per process, and a second SUMO run in a process after one
that removed vehicles can crash libsumo). Workers are started with the ``spawn`` method and
talk over pipes; every answer (and the write of every large request) is awaited with a timeout,
so a worker that dies, hangs or is stopped raises :class:`VecEnvWorkerError` naming the scene
instead of hanging the trainer.

Slots: scene ``k`` owns ``slots[k]`` consecutive slots, as many as its agents can ever be alive
at once (from the recorded track lifetimes). An agent joining takes the lowest free slot of its
scene and keeps it until it leaves; then the slot is free until another agent joins.
``infos[i]["slot_active"]`` (and :attr:`MultiSceneVecEnv.slot_active`) says whether slot ``i``
holds an agent; the observation of a free slot is zeros and its action is ignored. Learning
must drop free slot-steps (see :class:`magail_sumo.training.ppo.MaskedRolloutBuffer`): they are
not transitions. ``dones[i]`` is True when the slot's agent left (with
``infos[i]["terminal_observation"]``, ``"TimeLimit.truncated"`` when it was truncated, not
terminated, and ``"reason"``) and also when a free slot is given to a new agent, so GAE never
runs from one agent into another. When a scene has no agents left it is reset (next episode
seed) inside the same step. :attr:`MultiSceneVecEnv.slot_pos` is each slot's pose for the
current observation (x, y in m, yaw in rad; scene frame; the agent's bicycle state, zeros for a
free slot), sent by the workers as one small (slots, 3) float32 array per step.

Determinism: episode ``e`` of scene ``k`` is reset with seed ``seed + 100_003·k + e``; with
``EnvConfig.start_window: random`` its start step is drawn from :func:`episode_rng` of that
worker's seed ``seed + 100_003·k`` and ``e`` (a pure function of the two); every
worker logs the actions of its current episode, so :meth:`MultiSceneVecEnv.get_state` /
:meth:`~MultiSceneVecEnv.set_state` restore the exact simulation state in fresh workers by
replaying them (used for exact training resume).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import threading
import traceback
from multiprocessing.reduction import ForkingPickler
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn

from magail_sumo.errors import MagailSumoError

from .config import EnvConfig, draw_start

SEED_STRIDE = 100_003
#: per-step cost of a scene worker in units of one agent's cost (SUMO step, log replay, sensor
#: set-up: about 1 ms of fixed work per step against about 0.1 ms per agent, measured on the
#: bundled scenes); used to balance workers over cores
WORKER_FIXED_COST = 10.0
#: messages up to this size go into an empty pipe without blocking (Linux pipes hold 64 KiB)
_PIPE_SAFE_BYTES = 16 * 1024


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
    """The :class:`~magail_sumo.scene.Scene` a spec names."""
    from converters import iter_scenes

    for scene in iter_scenes(spec.scene_file):
        if spec.scenario_id is None or scene.scenario_id == spec.scenario_id:
            return scene
    raise VecEnvWorkerError(f"{spec.scene_file}: no scene {spec.scenario_id}")


def episode_rng(seed: int, episode: int) -> np.random.Generator:
    """The generator drawing episode ``episode``'s start window of a worker seeded ``seed``."""
    return np.random.default_rng(np.random.SeedSequence([seed % (1 << 64), episode]))


def max_concurrent_agents(env) -> int:
    """Upper bound of the number of agents of ``env`` alive at one step (>= 1), over every
    episode window its config allows (``start_window: random``: over the whole log; never
    more than K with ``controlled: K``)."""
    tr = env.scene.tracks
    row_of = {int(t): k for k, t in enumerate(tr.id.tolist())}
    rows = np.array([row_of[int(a)] for a in env.possible_agents], np.int64)
    if rows.size == 0:
        return 1
    cfg = env.config
    t_steps = tr.valid.shape[1]
    if cfg.start_window == "random":  # every window lies in the log; tracks join no earlier
        start, end = 0, t_steps - 1
    else:
        start = min(cfg.start_step, t_steps - 1)
        end = t_steps - 1 if cfg.max_steps is None else min(t_steps - 1, start + cfg.max_steps)
    valid = tr.valid[rows]
    steps = np.arange(t_steps)
    join = np.where(valid & (steps[None] >= start), steps[None], t_steps).min(axis=1)
    last = t_steps - 1 - np.argmax(valid[:, ::-1], axis=1)
    alive = (steps[None] >= join[:, None]) & (steps[None] <= last[:, None]) & \
        (steps[None] <= end)
    most = int(alive.sum(axis=0).max())
    if not isinstance(cfg.controlled, str):
        most = min(most, int(cfg.controlled))
    return max(1, most)


# ---------------------------------------------------------------------------------- worker side
class _SlotEnv:
    """The env of one scene with its slot bookkeeping (runs in the worker process)."""

    def __init__(self, spec: SceneSpec, config: EnvConfig, seed: int, slots: int | None) -> None:
        from .driving_env import SumoDrivingEnv

        self.env = SumoDrivingEnv(load_spec_scene(spec), spec.bundle, config)
        self.slots = slots or max_concurrent_agents(self.env)
        self.dim = int(self.env.observation_space(self.env.possible_agents[0]).shape[0]) \
            if self.env.possible_agents else 0
        self.base_seed = seed
        self.episode = -1
        self.actions: list[np.ndarray] = []
        self.names: list[str | None] = [None] * self.slots
        self.slot_of: dict[str, int] = {}  #: agent name -> its slot (the agents in slots)

    def _assign(self, obs: dict[str, np.ndarray], packet: dict) -> None:
        slot_of, names = self.slot_of, self.names
        for name in self.env.agents:
            if name in slot_of:
                continue
            try:
                k = names.index(None)
            except ValueError:
                raise VecEnvWorkerError(f"{self.env.scene.scenario_id}: more than {self.slots} "
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
                "agent_steps": 0}

    def _active(self) -> np.ndarray:
        active = np.zeros(self.slots, bool)
        active[list(self.slot_of.values())] = True
        return active

    def _reset(self, packet: dict) -> None:
        self.episode += 1
        self.actions = []
        self.names = [None] * self.slots
        self.slot_of = {}
        cfg = self.env.config
        options = None
        if cfg.start_window == "random":
            options = {"start_step": draw_start(cfg, self.env.scene.num_steps,
                                                episode_rng(self.base_seed, self.episode))}
        obs, _ = self.env.reset(seed=self.base_seed + self.episode, options=options)
        self._assign(obs, packet)

    def reset(self) -> dict:
        self.episode = -1
        packet = self._packet()
        self._reset(packet)
        packet["dones"][:] = False
        packet["active"] = self._active()
        return packet

    def step(self, actions: np.ndarray) -> dict:
        actions = np.asarray(actions, np.float32).reshape(self.slots, 2)
        self.actions.append(actions.copy())
        packet = self._packet()
        acts = {n: actions[k] for n, k in self.slot_of.items()}
        packet["agent_steps"] = len(acts)
        obs, _, terms, truncs, infos = self.env.step(acts)
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
        packet["active"] = self._active()
        return packet

    def restore(self, episode: int, actions: Sequence[np.ndarray]) -> dict:
        """Reset to ``episode`` and replay ``actions``: the state :meth:`state` described."""
        self.episode = episode - 1
        packet = self._packet()
        self._reset(packet)
        for a in actions:
            packet = self.step(a)
        packet["active"] = self._active()
        return packet

    def state(self) -> tuple[int, list[np.ndarray]]:
        return self.episode, [a.copy() for a in self.actions]


def _worker(conn, spec: SceneSpec, config: EnvConfig, seed: int, slots: int | None) -> None:
    try:
        senv = _SlotEnv(spec, config, seed, slots)
        conn.send(("ok", {"slots": senv.slots, "dim": senv.dim,
                          "possible_agents": list(senv.env.possible_agents)}))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent
        conn.send(("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"))
        return
    while True:
        try:
            cmd, arg = conn.recv()
        except (EOFError, KeyboardInterrupt):
            break
        try:
            if cmd == "step":
                out = senv.step(arg)
            elif cmd == "reset":
                out = senv.reset()
            elif cmd == "state":
                out = senv.state()
            elif cmd == "restore":
                out = senv.restore(*arg)
            elif cmd == "call":
                name, args, kwargs = arg
                out = getattr(senv.env, name)(*args, **kwargs)
            elif cmd == "getattr":
                out = getattr(senv.env, arg)
            elif cmd == "close":
                senv.env.close()
                conn.send(("ok", None))
                break
            else:
                raise ValueError(f"unknown command {cmd!r}")
            conn.send(("ok", out))
        except BaseException as exc:  # noqa: BLE001 - reported to the parent
            conn.send(("error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"))
    conn.close()


# ---------------------------------------------------------------------------------- parent side
class MultiSceneVecEnv(VecEnv):
    """Agents of several scenes as SB3 vector slots, one worker process per scene (module doc).

    :param scenes: the scenes (scene file + bundle folder each).
    :param config: env configuration shared by all scenes.
    :param seed: base seed of the episode seeds.
    :param slots: slots per scene (None: each scene's max concurrent agents).
    :param timeout_s: seconds to wait for any worker answer before giving up on it.
    :param start_method: ``"spawn"`` or ``"forkserver"``.
    :param pin_workers: pin each worker process to one core, balancing the scenes' per-step cost
        (:func:`place_workers`, cost = fixed + slots); the trainer process stays unpinned. Helps
        when there are more scenes than cores (a big scene keeps a core to itself instead of
        being time-shared). Meant for a machine dedicated to one run: concurrent runs pinning
        their workers would stack them on the same cores. Linux only, ignored elsewhere.
    """

    def __init__(self, scenes: Sequence[SceneSpec], config: EnvConfig | None = None,
                 seed: int = 0, slots: Sequence[int] | None = None, timeout_s: float = 120.0,
                 start_method: str = "spawn", pin_workers: bool = False) -> None:
        if not scenes:
            raise ValueError("MultiSceneVecEnv needs at least one scene")
        from magail_sumo.sensors.observation import observation_bounds

        self.specs = list(scenes)
        self.config = config or EnvConfig()
        self.seed_base = seed
        self.timeout_s = timeout_s
        ctx = mp.get_context(start_method)
        self._conns, self._procs = [], []
        self.closed = False
        try:
            for k, spec in enumerate(self.specs):
                parent, child = ctx.Pipe()
                proc = ctx.Process(target=_worker, daemon=True, name=f"scene-{spec.name}",
                                   args=(child, spec, self.config, seed + SEED_STRIDE * k,
                                         None if slots is None else slots[k]))
                proc.start()
                child.close()
                self._conns.append(parent)
                self._procs.append(proc)
            hello = [self._recv(k) for k in range(len(self.specs))]
        except BaseException:
            self._kill_all()
            raise
        self.slots = [h["slots"] for h in hello]
        #: CPU set of each worker (empty: not pinned)
        self.worker_cpus: list[set[int]] = [set() for _ in self.specs]
        if pin_workers and hasattr(os, "sched_setaffinity"):
            self.worker_cpus = place_workers([WORKER_FIXED_COST + n for n in self.slots],
                                             os.sched_getaffinity(0))
            for proc, cpus in zip(self._procs, self.worker_cpus):
                try:
                    os.sched_setaffinity(proc.pid, cpus)
                except OSError:  # the process is gone (reported by the next answer) or denied
                    pass
        self.possible_agents = [h["possible_agents"] for h in hello]
        dims = {h["dim"] for h in hello if h["dim"]}
        low, high = observation_bounds(self.config.observation)
        if dims - {low.shape[0]}:
            raise VecEnvWorkerError(f"observation sizes {sorted(dims)} differ from the config's "
                                    f"{low.shape[0]}")
        self.obs_dim = int(low.shape[0])
        offsets = np.concatenate([[0], np.cumsum(self.slots)])
        self.scene_slices = [slice(int(a), int(b)) for a, b in zip(offsets[:-1], offsets[1:])]
        n = int(offsets[-1])
        #: (num_envs,) scene index of each slot
        self.slot_scene = np.repeat(np.arange(len(self.specs)), self.slots)
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
        self._actions: np.ndarray | None = None
        super().__init__(n, spaces.Box(low, high, dtype=np.float32),
                         spaces.Box(-1.0, 1.0, (2,), np.float32))

    # ------------------------------------------------------------------ pipes
    def _recv(self, k: int) -> Any:
        conn, proc, name = self._conns[k], self._procs[k], self.specs[k].name
        try:
            ready = conn.poll(self.timeout_s)
        except (OSError, EOFError):
            ready = True
        if not ready:
            self._kill_all()
            raise VecEnvWorkerError(f"scene {name}: worker did not answer within "
                                    f"{self.timeout_s:g} s (killed)")
        try:
            status, payload = conn.recv()
        except (EOFError, OSError, ConnectionError):
            proc.join(1.0)
            code = proc.exitcode
            self._kill_all()
            raise VecEnvWorkerError(f"scene {name}: worker process died (exit code {code})") \
                from None
        if status != "ok":
            self._kill_all()
            raise VecEnvWorkerError(f"scene {name}: worker failed: {payload}")
        return payload

    def _send(self, k: int, msg: tuple) -> None:
        """Send ``msg`` to worker ``k``. Requests and answers alternate, so the pipe is empty
        here and a small message never blocks; a large one (a ``restore`` replay) is written
        from a thread and waited for at most ``timeout_s`` (a stopped worker reads nothing)."""
        conn = self._conns[k]
        try:
            buf = ForkingPickler.dumps(msg)
            if len(buf) <= _PIPE_SAFE_BYTES:
                conn.send_bytes(buf)
            else:
                failed: list[BaseException] = []

                def write() -> None:
                    try:
                        conn.send_bytes(buf)
                    except BaseException as exc:  # noqa: BLE001 - re-raised below
                        failed.append(exc)

                writer = threading.Thread(target=write, daemon=True)
                writer.start()
                writer.join(self.timeout_s)
                if writer.is_alive():
                    self._kill_all()  # closes the pipe: the writer thread ends
                    raise VecEnvWorkerError(f"scene {self.specs[k].name}: worker did not read "
                                            f"its request within {self.timeout_s:g} s (killed)")
                if failed:
                    raise failed[0]
        except (BrokenPipeError, OSError, ConnectionError):
            code = self._procs[k].exitcode
            self._kill_all()
            raise VecEnvWorkerError(f"scene {self.specs[k].name}: worker process died "
                                    f"(exit code {code})") from None

    def _kill_all(self) -> None:
        for proc in self._procs:
            if proc.is_alive():
                proc.terminate()
        for proc in self._procs:
            proc.join(2.0)
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)
        for conn in self._conns:
            conn.close()
        self.closed = True

    def _broadcast(self, cmd: str, args: Sequence[Any]) -> list[Any]:
        if self.closed:
            raise VecEnvWorkerError("the vector env is closed")
        for k, arg in enumerate(args):
            self._send(k, (cmd, arg))
        return [self._recv(k) for k in range(len(self.specs))]

    # ------------------------------------------------------------------ VecEnv API
    def _collect(self, packets: list[dict], step: bool) -> tuple:
        obs = np.concatenate([p["obs"] for p in packets])
        dones = np.concatenate([p["dones"] for p in packets])
        active = np.concatenate([p["active"] for p in packets])
        pos = np.concatenate([p["pos"] for p in packets])
        infos: list[dict[str, Any]] = [{"slot_active": bool(a), "scene": int(s)}
                                       for a, s in zip(active, self.slot_scene)]
        for k, p in enumerate(packets):
            base = self.scene_slices[k].start
            for j, info in p["infos"].items():
                infos[base + j].update(info)
            if step:
                self.agent_steps += p["agent_steps"]
                self.episodes += p["episodes"]
        self.prev_slot_active = self.slot_active
        self.slot_active = active
        self.prev_slot_pos = self.slot_pos
        self.slot_pos = pos
        return obs, dones, infos

    def reset(self) -> np.ndarray:
        packets = self._broadcast("reset", [None] * len(self.specs))
        obs, _, infos = self._collect(packets, step=False)
        self.prev_slot_active = np.zeros(self.num_envs, bool)
        self.prev_slot_pos = np.zeros((self.num_envs, 3), np.float32)
        self.reset_infos = infos
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions, np.float32).reshape(self.num_envs, 2)

    def step_wait(self) -> VecEnvStepReturn:
        acts = self._actions
        packets = self._broadcast("step", [acts[s] for s in self.scene_slices])
        obs, dones, infos = self._collect(packets, step=True)
        return obs, np.zeros(self.num_envs, np.float32), dones, infos

    def get_state(self) -> list[tuple[int, list[np.ndarray]]]:
        """Per scene (episode index, actions since its reset): enough to rebuild the state."""
        return self._broadcast("state", [None] * len(self.specs))

    def set_state(self, state: Sequence[tuple[int, list[np.ndarray]]]) -> np.ndarray:
        """Rebuild the state :meth:`get_state` gave (replaying actions); the observation."""
        if len(state) != len(self.specs):
            raise ValueError(f"state has {len(state)} scenes, the env {len(self.specs)}")
        packets = self._broadcast("restore", list(state))
        obs, _, infos = self._collect(packets, step=False)
        self.prev_slot_active = np.zeros(self.num_envs, bool)
        self.prev_slot_pos = np.zeros((self.num_envs, 3), np.float32)
        self.reset_infos = infos
        return obs

    def close(self) -> None:
        if self.closed:
            return
        for k in range(len(self.specs)):
            try:
                self._conns[k].send(("close", None))
            except (BrokenPipeError, OSError):
                pass
        for k, proc in enumerate(self._procs):
            try:
                if self._conns[k].poll(5.0):
                    self._conns[k].recv()
            except (EOFError, OSError):
                pass
            proc.join(5.0)
        self._kill_all()

    def _scenes_of(self, indices: VecEnvIndices) -> list[int]:
        return sorted({int(self.slot_scene[i]) for i in self._get_indices(indices)})

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        """Attribute of the scene env of each slot of ``indices``."""
        scenes = self._scenes_of(indices)
        for k in scenes:
            self._send(k, ("getattr", attr_name))
        got = {k: self._recv(k) for k in scenes}
        return [got[int(self.slot_scene[i])] for i in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        raise NotImplementedError("scene envs are configured through EnvConfig")

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None,
                   **method_kwargs) -> list[Any]:
        scenes = self._scenes_of(indices)
        for k in scenes:
            self._send(k, ("call", (method_name, method_args, method_kwargs)))
        got = {k: self._recv(k) for k in scenes}
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
    (:func:`converters.sumo.scenario.claim_networks_dir`). Two scenes whose ids map to one name
    are refused (:class:`~magail_sumo.outputs.OutputError`).

    :param errors: when given, a scene (or file) that cannot be used is appended here as a
        one-line reason and left out, instead of raising :class:`MagailSumoError`.
    """
    from converters import iter_scenes
    from magail_sumo.outputs import NameRegistry, inside, printable

    networks = Path(networks)
    names = NameRegistry()
    out = []

    def fail(msg: str) -> None:
        if errors is None:
            raise MagailSumoError(msg)
        errors.append(msg)

    for f in scene_files:
        try:
            for scene in iter_scenes(f):
                sid = scene.scenario_id
                folder = inside(networks, names.name(sid))
                if not (folder / f"{folder.name}.sumocfg").is_file():
                    if not convert_missing:
                        fail(f"{folder}: no converted bundle for scene {printable(sid)}")
                        continue
                    from converters.sumo.scenario import (ConvertOptions, claim_networks_dir,
                                                          convert_scene)

                    claim_networks_dir(networks)
                    rep = convert_scene(scene, networks, ConvertOptions(
                        baseline=False, time_budget_s=time_budget_s))
                    if rep.status != "ok":
                        fail(f"{f}: scene {printable(sid)} could not be converted: {rep.reason}")
                        continue
                out.append(SceneSpec(str(f), str(folder), sid))
        except Exception as exc:  # noqa: BLE001 - an unreadable file
            if errors is None:
                raise
            errors.append(printable(f"{f}: " + (str(exc) if isinstance(exc, MagailSumoError)
                                                 else f"{type(exc).__name__}: {exc}"), 400))
    return out
