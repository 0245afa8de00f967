"""How the vector env talks to its scene workers: one worker object, several backends.

A scene worker (:class:`~magail_sumo.env.slot_worker.SlotWorker`, one SUMO each) answers requests
``(command, argument)`` with ``("ok", payload)`` or ``("error", one-line text + traceback)``. A
*backend* runs workers somewhere and carries the requests: :class:`WorkerHandle` is its whole
interface (start, send, receive with a timeout, kill). Backends are registered in
:data:`BACKENDS` by import path, so a backend's dependencies are imported only when it is used:

* ``process`` (:class:`ProcessWorker`): a local process per worker (``spawn`` or
  ``forkserver``) over a pipe; nothing to install or start;
* ``hosted`` (:class:`magail_sumo.env.hosted_workers.HostedWorker`): several workers per
  local process (one process per core), a step's requests to a process in one message;
* ``ray`` (:class:`magail_sumo.env.ray_workers.RayWorker`): a Ray actor per worker, on any
  node of a Ray cluster (the ``ray`` extra).

A worker that dies or does not answer in time raises :class:`WorkerLost` (the vector env may
replace it); an error answer raises :class:`WorkerFailed` (deterministic: never retried).
"""

from __future__ import annotations

import importlib
import multiprocessing as mp
import threading
import traceback
from multiprocessing.reduction import ForkingPickler
from typing import Any

from magail_sumo.errors import MagailSumoError
from magail_sumo.workers import share_cores

#: messages up to this size go into an empty pipe without blocking (Linux pipes hold 64 KiB)
_PIPE_SAFE_BYTES = 16 * 1024

#: backend name -> "module:class" of its :class:`WorkerHandle`
BACKENDS = {
    "process": "magail_sumo.env.transport:ProcessWorker",
    "hosted": "magail_sumo.env.hosted_workers:HostedWorker",
    "ray": "magail_sumo.env.ray_workers:RayWorker",
}


class WorkerLost(MagailSumoError):
    """A worker died or did not answer (or read its request) in time."""


class WorkerFailed(MagailSumoError):
    """A worker answered a request with an error: the message is the error's one line, the
    worker's traceback is kept in :attr:`worker_traceback` (printed with ``--debug``)."""

    def __init__(self, message: str, worker_traceback: str = "") -> None:
        super().__init__(message)
        self.worker_traceback = worker_traceback

    @classmethod
    def of(cls, name: str, payload: object) -> "WorkerFailed":
        """The failure of worker ``name`` from its ``serve`` error ``payload`` (the error's
        line, then its traceback)."""
        text = str(payload)
        line, _, rest = text.partition("\n")
        return cls(f"{name}: worker failed: {line}", rest)


def backend_class(name: str) -> type["WorkerHandle"]:
    """The :class:`WorkerHandle` class of backend ``name`` (:data:`BACKENDS`)."""
    try:
        module, cls = BACKENDS[name].split(":")
    except KeyError:
        raise ValueError(f"unknown worker backend {name!r} (known: "
                         f"{', '.join(sorted(BACKENDS))})") from None
    return getattr(importlib.import_module(module), cls)


def serve(worker_factory, args: tuple, cmd: str, arg: Any, state: dict) -> tuple[str, Any]:
    """Answer one request with the worker ``state["worker"]`` (built from
    ``worker_factory(*args)`` by the ``hello`` request); never raises. A scene worker is
    one of several processes on the cores: its numba kernels run on one thread
    (:func:`~magail_sumo.workers.share_cores`; per request, as the thread-local setting
    follows the thread a backend answers on)."""
    try:
        share_cores()
        if cmd == "hello":
            state["worker"] = worker_factory(*args)
            return "ok", state["worker"].hello()
        return "ok", state["worker"].handle(cmd, arg)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent
        return "error", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}"


class WorkerHandle:
    """One worker of a backend (the interface; see the module doc).

    :param name: shown in messages. :param factory: builds the worker object in the worker
        (a picklable top-level callable). :param args: its arguments.
    :param options: backend options (e.g. Ray's address and ``num_cpus``).
    """

    def __init__(self, name: str, factory, args: tuple, options: dict | None = None) -> None:
        self.name = name
        self.factory = factory
        self.args = args
        self.options = options or {}

    #: where the worker runs (a node id or host), for logs and tests
    node: str = ""
    #: the worker's OS process id where known
    pid: int | None = None

    def start(self) -> None:
        """Launch the worker and send it ``hello`` (answered by the next :meth:`recv`)."""
        raise NotImplementedError

    def send(self, cmd: str, arg: Any, timeout_s: float) -> None:
        raise NotImplementedError

    def recv(self, timeout_s: float) -> Any:
        """The answer to the last request; :class:`WorkerLost` / :class:`WorkerFailed`."""
        raise NotImplementedError

    def kill(self) -> None:
        """Stop the worker now (it may be dead already)."""
        raise NotImplementedError

    def close(self, timeout_s: float = 5.0) -> None:
        """Ask the worker to close its env and end; kill it if it does not."""
        raise NotImplementedError


# ------------------------------------------------------------------------------- process backend
def batch_scheduling() -> None:
    """Run this process under Linux's ``SCHED_BATCH`` policy (best effort; elsewhere a no-op).

    A scene worker is woken by each request; under the default policy the woken worker
    preempts the trainer in the middle of its loop of sends (it has just written to the
    worker's pipe), so on a machine with fewer cores than workers + trainer the trainer only
    reaches the next worker's request after the first worker's whole step. ``SCHED_BATCH``
    tasks do not preempt on wakeup: the trainer sends every request first, then the workers
    step side by side. Scheduling only: results are unchanged (measured in the README's
    Benchmarks section)."""
    import os

    try:
        os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    except (AttributeError, OSError):  # not Linux, or refused: keep the default policy
        pass


def write_bounded(conn, buf: bytes, timeout_s: float) -> bool:
    """Write the pickled message ``buf`` to pipe ``conn``: a small one at once (requests and
    answers alternate, so the pipe is empty and it never blocks), a large one (a ``restore``
    replay) from a thread waited for at most ``timeout_s`` (a stopped reader reads nothing);
    False when it was not written in time (the caller kills the reader, which ends the thread).
    A failed write raises its error."""
    if len(buf) <= _PIPE_SAFE_BYTES:
        conn.send_bytes(buf)
        return True
    failed: list[BaseException] = []

    def write() -> None:
        try:
            conn.send_bytes(buf)
        except BaseException as exc:  # noqa: BLE001 - re-raised below
            failed.append(exc)

    writer = threading.Thread(target=write, daemon=True)
    writer.start()
    writer.join(timeout_s)
    if writer.is_alive():
        return False
    if failed:
        raise failed[0]
    return True


def stop_process(proc) -> None:
    """Stop a worker process now: ``terminate``, then ``kill`` if it is still alive 2 s later."""
    if proc.is_alive():
        proc.terminate()
        proc.join(2.0)
        if proc.is_alive():
            proc.kill()
            proc.join(1.0)


def _process_main(conn, factory, args: tuple) -> None:
    batch_scheduling()
    state: dict = {}
    while True:
        try:
            cmd, arg = conn.recv()
        except (EOFError, KeyboardInterrupt, OSError):
            break
        if cmd == "close":
            if "worker" in state:
                try:
                    state["worker"].close()
                except BaseException:  # noqa: BLE001 - closing: nothing more to report
                    pass
            try:
                conn.send(("ok", None))
            except (BrokenPipeError, OSError):
                pass
            break
        answer = serve(factory, args, cmd, arg, state)
        try:
            conn.send(answer)
        except (BrokenPipeError, OSError):
            break
        if cmd == "hello" and answer[0] != "ok":
            break
    conn.close()


class ProcessWorker(WorkerHandle):
    """A worker in a local process over a pipe (option ``start_method``: ``spawn``)."""

    def start(self) -> None:
        ctx = mp.get_context(self.options.get("start_method", "spawn"))
        parent, child = ctx.Pipe()
        self.proc = ctx.Process(target=_process_main, daemon=True, name=self.name,
                                args=(child, self.factory, self.args))
        self.proc.start()
        child.close()
        self.conn = parent
        self.pid = self.proc.pid
        self.node = "local"
        self.send("hello", None, 60.0)

    def send(self, cmd: str, arg: Any, timeout_s: float) -> None:
        """The request, written by :func:`write_bounded` (a large one waited for at most
        ``timeout_s``)."""
        try:
            if not write_bounded(self.conn, ForkingPickler.dumps((cmd, arg)), timeout_s):
                self.kill()  # closes the pipe: the writer thread ends
                raise WorkerLost(f"{self.name}: worker did not read its request within "
                                 f"{timeout_s:g} s (killed)")
        except (BrokenPipeError, OSError, ConnectionError):
            code = self.proc.exitcode
            self.kill()
            raise WorkerLost(f"{self.name}: worker process died (exit code {code})") from None

    def recv(self, timeout_s: float) -> Any:
        try:
            ready = self.conn.poll(timeout_s)
        except (OSError, EOFError):
            ready = True
        if not ready:
            self.kill()
            raise WorkerLost(f"{self.name}: worker did not answer within {timeout_s:g} s "
                             "(killed)")
        try:
            status, payload = self.conn.recv()
        except (EOFError, OSError, ConnectionError):
            self.proc.join(1.0)
            code = self.proc.exitcode
            self.kill()
            raise WorkerLost(f"{self.name}: worker process died (exit code {code})") from None
        if status != "ok":
            raise WorkerFailed.of(self.name, payload)
        return payload

    def kill(self) -> None:
        proc = getattr(self, "proc", None)
        if proc is None:
            return
        stop_process(proc)
        self.conn.close()

    def close(self, timeout_s: float = 5.0) -> None:
        proc = getattr(self, "proc", None)
        if proc is None:
            return
        try:
            self.conn.send(("close", None))
            if self.conn.poll(timeout_s):
                self.conn.recv()
        except (BrokenPipeError, EOFError, OSError):
            pass
        proc.join(timeout_s)
        self.kill()
