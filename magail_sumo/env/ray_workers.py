"""Ray backend of the scene workers: one Ray actor per worker, anywhere on a Ray cluster.

``workers.backend: ray`` in a training config. The learner stays in the driver (the
``magail-sumo train`` process); each scene worker (:class:`~magail_sumo.env.slot_worker.SlotWorker`,
one SUMO) is an actor with ``num_cpus`` CPUs (default 1), spread over the cluster's nodes
(``SPREAD`` scheduling). The requests and answers are the process backend's, so with the same
seeds both backends produce the same rollouts.

Cluster: ``address`` None starts a local Ray in the driver (``ray.init()``); otherwise the
driver connects to a running cluster (``ray start --head`` on one machine, ``ray start
--address HEAD:6379`` on the others; the address is ``HEAD:6379`` or ``auto``). An address
that does not answer fails at once with one line. Every node needs magail_sumo installed and
the scene files at the same paths (bundles are converted on demand on the node that plays a
scene, into ``scenes.networks`` — shared or per node).

Faults: a dead actor (its node lost, its process killed) or one that does not answer within
the timeout is killed and replaced by the vector env (its episode replayed), like a process
worker; Ray's own actor restarts are off so that only one mechanism acts.
"""

from __future__ import annotations

import socket
from typing import Any

from magail_sumo.errors import MagailSumoError

from .transport import WorkerFailed, WorkerHandle, WorkerLost, serve

_ACTOR_CLASS = None


class RayUnavailable(MagailSumoError):
    """Ray is not installed or its cluster cannot be reached."""


def _ray():
    try:
        import ray
    except ImportError:
        raise RayUnavailable("workers.backend 'ray' needs Ray: pip install -e \".[ray]\""
                             ) from None
    return ray


def _reachable(address: str, timeout_s: float = 5.0) -> str | None:
    """None when ``HOST:PORT`` accepts a TCP connection, else why not."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        return "expected HOST:PORT or 'auto'"
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            return None
    except OSError as exc:
        return exc.strerror or str(exc) or type(exc).__name__


def init_ray(address: str | None = None, cpus: float | None = None) -> None:
    """Start a local Ray (``address`` None; with at least ``cpus`` logical CPUs, so that every
    worker actor can be placed on this machine) or connect to the cluster at ``address``, once
    per process; :class:`RayUnavailable` (one line) when it cannot be reached."""
    import math
    import os

    ray = _ray()
    if ray.is_initialized():
        return
    if address not in (None, "auto", "local"):
        why = _reachable(address)
        if why is not None:
            raise RayUnavailable(f"workers.ray.address {address}: no Ray cluster answers there "
                                 f"({why}); start one with `ray start --head` or fix the address")
    local = {} if address not in (None, "local") else \
        {"num_cpus": max(os.cpu_count() or 1, math.ceil(cpus or 0))}
    try:
        ray.init(address=None if address == "local" else address, include_dashboard=False,
                 log_to_driver=False, logging_level="ERROR", configure_logging=False, **local)
    except Exception as exc:  # noqa: BLE001 - Ray raises many types here
        text = " ".join(str(exc).split())[:300]
        raise RayUnavailable(f"workers.ray.address {address or '(local)'}: cannot start or "
                             f"connect to Ray ({type(exc).__name__}: {text})") from None


def _actor_class():
    global _ACTOR_CLASS
    if _ACTOR_CLASS is None:
        ray = _ray()

        class SceneWorkerActor:
            """Holds one scene worker; answers the vector env's requests."""

            def __init__(self, factory, args: tuple) -> None:
                self.factory, self.args, self.state = factory, args, {}

            def request(self, cmd: str, arg: Any) -> tuple[str, Any]:
                if cmd == "close":
                    if "worker" in self.state:
                        self.state["worker"].close()
                    return "ok", None
                return serve(self.factory, self.args, cmd, arg, self.state)

            def where(self) -> tuple[str, str, int]:
                import os

                return ray.get_runtime_context().get_node_id(), socket.gethostname(), os.getpid()

        _ACTOR_CLASS = ray.remote(max_restarts=0, max_task_retries=0)(SceneWorkerActor)
    return _ACTOR_CLASS


class RayWorker(WorkerHandle):
    """A scene worker as a Ray actor (options: ``address``, ``num_cpus``)."""

    @classmethod
    def prepare(cls, options: dict, workers: int) -> None:
        """Start or join Ray; :class:`RayUnavailable` when the cluster has too few CPUs for
        the workers' actors (they would wait forever to be placed)."""
        need = workers * float(options.get("num_cpus", 1.0))
        init_ray(options.get("address"), need)
        have = float(_ray().cluster_resources().get("CPU", 0.0))
        if have < need:
            raise RayUnavailable(
                f"the Ray cluster has {have:g} CPUs; {workers} scene workers of "
                f"{float(options.get('num_cpus', 1.0)):g} CPU each need {need:g} "
                "(lower workers.count or workers.ray.num_cpus, or add nodes)")

    def start(self) -> None:
        ray = _ray()
        self.actor = _actor_class().options(
            num_cpus=float(self.options.get("num_cpus", 1.0)),
            scheduling_strategy="SPREAD").remote(self.factory, self.args)
        self._ref = self.actor.request.remote("hello", None)
        self._where = self.actor.where.remote()
        self.node = ""
        self.pid = None
        self._ray = ray

    def _locate(self, timeout_s: float) -> None:
        if self._where is not None:
            self.node, _, self.pid = self._ray.get(self._where, timeout=timeout_s)
            self._where = None

    def send(self, cmd: str, arg: Any, timeout_s: float) -> None:
        try:
            self._ref = self.actor.request.remote(cmd, arg)
        except Exception as exc:  # noqa: BLE001 - a dead actor
            raise WorkerLost(f"{self.name}: Ray actor unusable ({type(exc).__name__})") from None

    def recv(self, timeout_s: float) -> Any:
        ray = self._ray
        from ray.exceptions import GetTimeoutError, RayActorError, RayError

        try:
            self._locate(timeout_s)
            status, payload = ray.get(self._ref, timeout=timeout_s)
        except GetTimeoutError:
            self.kill()
            raise WorkerLost(f"{self.name}: Ray actor did not answer within {timeout_s:g} s "
                             "(killed)") from None
        except RayActorError as exc:
            raise WorkerLost(f"{self.name}: Ray actor died ({type(exc).__name__})") from None
        except RayError as exc:
            raise WorkerLost(f"{self.name}: Ray actor lost ({type(exc).__name__}: "
                             f"{' '.join(str(exc).split())[:200]})") from None
        if status != "ok":
            raise WorkerFailed(f"{self.name}: worker failed: {payload}")
        return payload

    def kill(self) -> None:
        actor = getattr(self, "actor", None)
        if actor is not None:
            try:
                self._ray.kill(actor, no_restart=True)
            except Exception:  # noqa: BLE001 - already gone
                pass

    def close(self, timeout_s: float = 5.0) -> None:
        try:
            self._ray.get(self.actor.request.remote("close", None), timeout=timeout_s)
        except Exception:  # noqa: BLE001 - closing: best effort
            pass
        self.kill()
