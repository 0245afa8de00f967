"""Supervision of scene workers: start them on a backend, exchange requests with timeouts, and
replace a worker that dies, hangs or is stopped (the worker half of
:class:`~magail_sumo.env.vec_env.MultiSceneVecEnv`, whose other half is Stable-Baselines3's
``VecEnv`` API).

Workers run on a backend (:mod:`magail_sumo.env.transport`: local processes started with
``spawn`` over pipes, or Ray actors); every answer (and the write of every large request) is
awaited with a timeout, so a lost worker never hangs the trainer: it is replaced
(``max_restarts`` times in a row at most; the replacement replays the lost worker's episode
from its seed and logged actions, so the rollout goes on exactly as it would have) or the env
raises :class:`~magail_sumo.env.slot_worker.VecEnvWorkerError` naming the scene. Workers can be
pinned to cores (:func:`place_workers`).
"""

from __future__ import annotations

import os
from typing import Any, Sequence

import numpy as np

from .slot_worker import VecEnvWorkerError, make_worker
from .transport import WorkerFailed, WorkerLost, backend_class

SEED_STRIDE = 100_003  #: worker k's seed is ``seed + SEED_STRIDE * k``
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


class WorkerSupervisor:
    """The worker half of a vector env over scene workers (module doc). The env sets
    :attr:`specs` (one worker source each), :attr:`config`, :attr:`seed_base` and :attr:`log`,
    calls :meth:`_start_workers`, keeps each worker's episode for :meth:`_replay_state`, and
    talks to the workers through :meth:`_exchange` (or :meth:`_send` then :meth:`_gather`)."""

    def _start_workers(self, slots: Sequence[int] | None, timeout_s: float, start_method: str,
                       pin_workers: bool, backend: str, backend_options: dict | None,
                       max_restarts: int) -> list[dict]:
        """Start one worker per source of :attr:`specs` and wait for each one's hello (its
        ``slots``, ``possible_agents``, ``host``, ``pid``); pin them when asked. All are killed
        if one fails (:class:`WorkerStartError` naming it)."""
        self.timeout_s = timeout_s
        #: seconds a (re)started worker gets to start and replay its episode: at least a minute,
        #: as starting a process or actor, importing and building the scene take a while
        self.start_timeout_s = max(timeout_s, 60.0)
        self.backend = backend
        self.max_restarts = max_restarts
        self._handle_cls = backend_class(backend)
        self._backend_opts = dict(backend_options or {}, start_method=start_method)
        if hasattr(self._handle_cls, "prepare"):
            self._handle_cls.prepare(self._backend_opts, len(self.specs))
        self.closed = False
        self.restarts = 0  #: workers replaced so far
        self._handles = []
        self._slots_asked = None if slots is None else list(slots)
        try:
            for k in range(len(self.specs)):
                self._handles.append(self._new_handle(k))
            hello = []
            for k in range(len(self.specs)):
                try:  # the hello comes once the worker sized its slots and built its first env
                    hello.append(self._handles[k].recv(self.start_timeout_s))
                except (WorkerLost, WorkerFailed) as exc:
                    why = str(exc)
                    if "did not answer" in why:
                        why += (" while starting (importing, reading the first scenes of its "
                                "shard to size its slots, building its first env)")
                    raise WorkerStartError(why, k) from None
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
        return hello

    def _replay_state(self, k: int) -> tuple[int, list[np.ndarray]]:
        """Worker ``k``'s episode index and the actions since that episode's reset (what a
        replacement replays); the env keeps them."""
        raise NotImplementedError

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
        episode, acts = self._replay_state(k)
        self._handles[k].send("restore", (episode, acts), self.start_timeout_s)
        self._handles[k].recv(self.start_timeout_s)
        self.restarts += 1
        self.log(f"worker {k} ({self.specs[k].name}) lost: {reason.splitlines()[0]}; replaced "
                 f"on {self._handles[k].node or 'local'}, episode {episode} replayed "
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


__all__ = ["SEED_STRIDE", "WORKER_FIXED_COST", "WorkerStartError", "WorkerSupervisor",
           "place_workers"]
