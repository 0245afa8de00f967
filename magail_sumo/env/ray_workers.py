"""Ray backend of the scene workers: one Ray actor per worker, anywhere on a Ray cluster.

``workers.backend: ray`` in a training config. The learner stays in the driver (the
``magail-sumo train`` process); each scene worker (:class:`~magail_sumo.env.slot_worker.SlotWorker`,
one SUMO) is an actor with ``num_cpus`` CPUs (default 1), spread over the cluster's nodes
(``SPREAD`` scheduling). The requests and answers are the process backend's, so with the same
seeds both backends produce the same rollouts.

Cluster: ``address`` None starts a local Ray in the driver, bound to 127.0.0.1 (every Ray
server socket on loopback: nothing outside this machine can attach a driver or join it) unless
``node_ip`` names an interface; otherwise the driver connects to a running cluster (``ray start
--head`` on one machine, ``ray start --address HEAD:6379`` on the others; the address is
``HEAD:6379`` or ``auto``). An address that does not accept connections, or whose service does
not answer as a Ray cluster's head (a gRPC probe bounded by :data:`PROBE_TIMEOUT_S`), fails
within seconds with one line. Every node needs magail_sumo installed and the scene files at the
same paths (bundles are converted on demand on the node that plays a scene, into
``scenes.networks`` — shared or per node).

Faults: a dead actor (its node lost, its process killed) or one that does not answer within
the timeout is killed and replaced by the vector env (its episode replayed), like a process
worker; Ray's own actor restarts are off so that only one mechanism acts.
"""

from __future__ import annotations

import contextlib
import os
import re
import socket
from typing import Any

from magail_sumo.errors import MagailSumoError

from .transport import WorkerFailed, WorkerHandle, WorkerLost, serve

_ACTOR_CLASS = None

#: seconds :func:`init_ray` waits for a cluster address to accept a connection, and then for
#: its service to answer the gRPC probe of a Ray head
PROBE_TIMEOUT_S = 5.0
#: the node IP of a local Ray that keeps every server socket on loopback
LOOPBACK = "127.0.0.1"


class RayUnavailable(MagailSumoError):
    """Ray is not installed or its cluster cannot be reached."""


def _ray():
    try:
        import ray
    except ImportError:
        raise RayUnavailable("workers.backend 'ray' needs Ray: pip install -e \".[ray]\""
                             ) from None
    return ray


def _reachable(address: str, timeout_s: float = PROBE_TIMEOUT_S) -> str | None:
    """None when ``HOST:PORT`` accepts a TCP connection, else why not."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        return "expected HOST:PORT or 'auto'"
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            return None
    except OSError as exc:
        return exc.strerror or str(exc) or type(exc).__name__


def _tls_credentials():
    """gRPC client credentials from Ray's TLS variables (``RAY_USE_TLS`` 1/true: the PEM files
    ``RAY_TLS_SERVER_CERT``, ``RAY_TLS_SERVER_KEY``, ``RAY_TLS_CA_CERT``, as Ray reads them);
    None without TLS; :class:`RayUnavailable` (one line) when a file is missing."""
    import grpc

    if os.environ.get("RAY_USE_TLS", "0").lower() not in ("1", "true"):
        return None
    pem = {}
    for var in ("RAY_TLS_SERVER_CERT", "RAY_TLS_SERVER_KEY", "RAY_TLS_CA_CERT"):
        try:
            with open(os.environ[var], "rb") as f:
                pem[var] = f.read()
        except (KeyError, OSError) as exc:
            why = "not set" if isinstance(exc, KeyError) else (exc.strerror or str(exc))
            raise RayUnavailable(f"RAY_USE_TLS is set but {var} cannot be read ({why})"
                                 ) from None
    return grpc.ssl_channel_credentials(root_certificates=pem["RAY_TLS_CA_CERT"],
                                        private_key=pem["RAY_TLS_SERVER_KEY"],
                                        certificate_chain=pem["RAY_TLS_SERVER_CERT"])


def _probe_head(address: str, timeout_s: float = PROBE_TIMEOUT_S) -> str | None:
    """None when the service at ``HOST:PORT`` answers as a Ray cluster's head, else why not
    (one clause, at most ``timeout_s`` seconds).

    The probe is one gRPC call of the head's cluster-id method
    (``ray.rpc.NodeInfoGcsService/GetClusterId``, empty request) over TLS when
    ``RAY_USE_TLS`` is set: a Ray head answers it, or refuses it as unauthenticated when the
    cluster uses token authentication (``ray.init`` then presents the token); any other
    service gives no gRPC answer in time (a silent listener), fails the HTTP/2 handshake (Redis,
    HTTP, anything not gRPC) or does not implement the method (another gRPC server, or a Ray
    port other than the head's)."""
    import grpc

    credentials = _tls_credentials()
    channel = (grpc.insecure_channel(address) if credentials is None
               else grpc.secure_channel(address, credentials))
    try:
        call = channel.unary_unary("/ray.rpc.NodeInfoGcsService/GetClusterId",
                                   request_serializer=lambda b: b,
                                   response_deserializer=lambda b: b)
        call(b"", timeout=timeout_s)
        return None
    except grpc.RpcError as exc:
        code = exc.code()
        if code == grpc.StatusCode.UNAUTHENTICATED:
            return None
        if code == grpc.StatusCode.DEADLINE_EXCEEDED:
            return f"it accepts connections but gives no gRPC answer within {timeout_s:g} s"
        if code == grpc.StatusCode.UNIMPLEMENTED:
            return ("it is a gRPC service without a Ray head's methods; give the port of "
                    "`ray start --head --port`")
        details = " ".join(str(exc.details() or "").split())
        if code == grpc.StatusCode.UNAVAILABLE:  # keep gRPC's last error, not its preamble
            details = re.sub(r"^.*last error: (UNAVAILABLE: )?(ipv[46]:\S+: )?", "", details)
            tls = "" if credentials is not None else \
                "; a TLS cluster needs RAY_USE_TLS=1 and RAY_TLS_* here too"
            return f"it does not speak gRPC: {details[:120]}{tls}"
        return f"gRPC {code.name}: {details[:120]}"
    finally:
        channel.close()


@contextlib.contextmanager
def _node_ip_kept_on_loopback(ray):
    """While open, ``ray.init`` keeps a 127.0.0.1 ``_node_ip_address`` as it is.

    Ray binds its server sockets (GCS, raylet, object manager, workers, runtime-env agent) to
    loopback exactly when the node IP is 127.0.0.1, and to every interface otherwise; but
    ``ray.init`` replaces a 127.0.0.1 node IP by the machine's address unless
    ``ray._private.ray_constants.ENABLE_RAY_CLUSTER`` is false (its variable
    ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER`` is read once, when Ray is imported), the setting
    with which Ray keeps a single-machine Ray on loopback on macOS and Windows. The constant is
    restored on exit; a Ray without it is left as it is (:func:`init_ray` then checks the
    node IP Ray took)."""
    try:
        from ray._private import ray_constants
    except ImportError:
        ray_constants = None
    old = getattr(ray_constants, "ENABLE_RAY_CLUSTER", None)
    if old is None:
        yield
        return
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = old


def init_ray(address: str | None = None, cpus: float | None = None,
             node_ip: str | None = None) -> None:
    """Start a local Ray or connect to the cluster at ``address``, once per process;
    :class:`RayUnavailable` (one line) when it cannot be started or reached.

    ``address`` None or ``local``: a new local Ray (whatever ``RAY_ADDRESS`` says) with at
    least ``cpus`` logical CPUs, so that every worker actor can be placed on this machine. With
    ``node_ip`` None it is bound to 127.0.0.1: all its server sockets listen on loopback only
    (refused, with the Ray shut down, if the installed Ray took another node IP); with an
    address it runs on that interface and, as Ray does, listens on every interface.

    ``address`` ``HOST:PORT``: it must accept a TCP connection within
    :data:`PROBE_TIMEOUT_S` and its service must answer as a Ray head (:func:`_probe_head`,
    within :data:`PROBE_TIMEOUT_S` more) before ``ray.init`` connects, so a closed port, a
    typo or another service (Redis, HTTP, a silent listener) is refused within seconds instead
    of hanging in Ray's retries. ``auto`` is left to Ray. ``node_ip`` (when given) is the
    address this driver gives the cluster to reach it."""
    import math

    ray = _ray()
    if ray.is_initialized():
        return
    local = address in (None, "local")
    where = f"workers.ray.address {address or '(local)'}"
    if not local and address != "auto":
        why = _reachable(address)
        if why is not None:
            raise RayUnavailable(f"{where}: no Ray cluster answers there ({why}); start one "
                                 "with `ray start --head` or fix the address")
        why = _probe_head(address)
        if why is not None:
            raise RayUnavailable(f"{where}: the service there is not a Ray cluster ({why})")
    options: dict[str, Any] = {}
    if local:
        options["num_cpus"] = max(os.cpu_count() or 1, math.ceil(cpus or 0))
    if local or node_ip is not None:
        options["_node_ip_address"] = node_ip or LOOPBACK
    loopback = local and options["_node_ip_address"] == LOOPBACK
    try:
        with _node_ip_kept_on_loopback(ray) if loopback else contextlib.nullcontext():
            ray.init(address="local" if local else address, include_dashboard=False,
                     log_to_driver=False, logging_level="ERROR", configure_logging=False,
                     **options)
    except Exception as exc:  # noqa: BLE001 - Ray raises many types here
        text = " ".join(str(exc).split())[:300]
        raise RayUnavailable(f"{where}: cannot start or connect to Ray "
                             f"({type(exc).__name__}: {text})") from None
    if loopback:
        got = ray.util.get_node_ip_address()
        if got != LOOPBACK:
            ray.shutdown()
            raise RayUnavailable(
                f"{where}: Ray {ray.__version__} started on {got}, not on loopback; set "
                "workers.ray.node_ip to run a local Ray reachable on that interface")


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
    """A scene worker as a Ray actor (options: ``address``, ``num_cpus``, ``node_ip``: see
    :func:`init_ray`)."""

    @classmethod
    def prepare(cls, options: dict, workers: int) -> None:
        """Start or join Ray; :class:`RayUnavailable` when the cluster has too few CPUs for
        the workers' actors (they would wait forever to be placed)."""
        need = workers * float(options.get("num_cpus", 1.0))
        init_ray(options.get("address"), need, options.get("node_ip"))
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
            raise WorkerFailed.of(self.name, payload)
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
