"""Several scene workers in one local process: the ``hosted`` backend (``workers.backend:
hosted``).

The ``process`` backend starts one process per scene worker; a training run of the womd14
recipe has 10 workers on a 2-core machine, so each vector step costs the trainer 10 pipe
writes (each one wakes a process that competes with the trainer for the cores) and 10 reads.
This backend keeps one :class:`~magail_sumo.env.slot_worker.SlotWorker` per scene source, as
the process backend does (the same seeds, requests and answers, so the same rollouts), but
places the workers that run no SUMO (recorded scenes with log background and no SUMO mirror,
the training recipe's setting) round-robin in one process per usable core (at most one per
worker; option ``processes``): a step's requests to a process's workers go in one message once
each of them has one (or when the trainer waits for one of them), the process answers them in
order in one message. A worker that may run SUMO (:func:`~magail_sumo.env.slot_worker.
runs_sumo`: libsumo runs one simulation per process) and a worker started to replace a lost one
run in a process of their own.

Faults are the process backend's: a process that dies or does not answer in time loses every
worker it holds; each raises :class:`~magail_sumo.env.transport.WorkerLost` and the vector env
replaces it (its episode replayed). An error answer raises
:class:`~magail_sumo.env.transport.WorkerFailed` for that worker.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from multiprocessing.reduction import ForkingPickler
from typing import Any

from .slot_worker import runs_sumo
from .transport import (WorkerFailed, WorkerHandle, WorkerLost, batch_scheduling, serve,
                        stop_process, write_bounded)


def _host_main(conn) -> None:
    """A host process: answers batches of ``(member, command, argument)`` in order with one
    list of ``(member, answer)``; ends when its last member closed (or the pipe closes)."""
    batch_scheduling()
    members: dict[int, tuple[Any, tuple, dict]] = {}
    while True:
        try:
            batch = conn.recv()
        except (EOFError, KeyboardInterrupt, OSError):
            break
        out = []
        for i, cmd, arg in batch:
            if cmd == "hello":
                factory, args = arg
                members[i] = (factory, args, {})
                answer = serve(factory, args, "hello", None, members[i][2])
                if answer[0] != "ok":
                    del members[i]
            elif cmd == "close":
                state = members.pop(i, (None, None, {}))[2]
                if "worker" in state:
                    try:
                        state["worker"].close()
                    except BaseException:  # noqa: BLE001 - closing: nothing more to report
                        pass
                answer = ("ok", None)
            else:
                factory, args, state = members[i]
                answer = serve(factory, args, cmd, arg, state)
            out.append((i, answer))
        try:
            conn.send(out)
        except (BrokenPipeError, OSError):
            break
        if not members:
            break
    conn.close()


class _Host:
    """The parent's side of one host process: its members' requests not yet sent
    (:attr:`pending`), those sent and not answered (:attr:`sent`), answers read but not yet
    taken (:attr:`answers`)."""

    def __init__(self, ctx, name: str) -> None:
        self.ctx, self.name = ctx, name
        self.proc = None
        self.conn = None
        self.live: set[int] = set()  #: members started and not closed
        self.pending: dict[int, tuple[str, Any]] = {}
        self.sent: set[int] = set()
        self.answers: dict[int, tuple[str, Any]] = {}
        self.lost: str | None = None  #: why the process is gone (None: running)
        self._next = 0

    def add(self) -> int:
        """A new member's id (the process starts with the first one)."""
        if self.proc is None:
            parent, child = self.ctx.Pipe()
            self.proc = self.ctx.Process(target=_host_main, args=(child,), daemon=True,
                                         name=self.name)
            self.proc.start()
            child.close()
            self.conn = parent
        i, self._next = self._next, self._next + 1
        self.live.add(i)
        return i

    def _gone(self, why: str) -> WorkerLost:
        self.lost = self.lost or why
        self.kill()
        return WorkerLost(self.lost)

    def submit(self, i: int, cmd: str, arg: Any, timeout_s: float) -> None:
        """Queue member ``i``'s request; send the queue once no live member is idle."""
        if self.lost:
            raise WorkerLost(self.lost)
        self.pending[i] = (cmd, arg)
        if len(self.pending) + len(self.sent) >= len(self.live):
            self.flush(timeout_s)

    def flush(self, timeout_s: float) -> None:
        """Send the pending requests as one message (:func:`~magail_sumo.env.transport.
        write_bounded`: a large one waited for at most ``timeout_s``)."""
        if not self.pending:
            return
        batch = [(i, cmd, arg) for i, (cmd, arg) in sorted(self.pending.items())]
        self.sent.update(self.pending)
        self.pending = {}
        try:
            if not write_bounded(self.conn, ForkingPickler.dumps(batch), timeout_s):
                raise self._gone(f"{self.name}: worker process did not read its requests "
                                 f"within {timeout_s:g} s (killed)")
        except (BrokenPipeError, OSError, ConnectionError):
            code = self.proc.exitcode
            raise self._gone(f"{self.name}: worker process died (exit code {code})") from None

    def answer(self, i: int, timeout_s: float) -> tuple[str, Any]:
        """Member ``i``'s answer (its request is sent first if it still waits in the queue)."""
        if i in self.pending:
            self.flush(timeout_s)
        while i not in self.answers:
            if self.lost:
                raise WorkerLost(self.lost)
            try:
                ready = self.conn.poll(timeout_s)
            except (OSError, EOFError):
                ready = True
            if not ready:
                raise self._gone(f"{self.name}: worker process did not answer within "
                                 f"{timeout_s:g} s (killed)")
            try:
                got = self.conn.recv()
            except (EOFError, OSError, ConnectionError):
                self.proc.join(1.0)
                raise self._gone(f"{self.name}: worker process died (exit code "
                                 f"{self.proc.exitcode})") from None
            for j, ans in got:
                self.sent.discard(j)
                self.answers[j] = ans
        return self.answers.pop(i)

    def leave(self, i: int) -> None:
        self.live.discard(i)
        self.pending.pop(i, None)

    def kill(self) -> None:
        if self.proc is None:
            return
        stop_process(self.proc)
        self.conn.close()
        self.lost = self.lost or f"{self.name}: worker process killed"


class _HostPool:
    """The host processes of one vector env: of the first ``workers`` members, those that
    may share placed round-robin over ``processes`` hosts; the others and every later one (a
    replacement) each in a new host."""

    def __init__(self, workers: int, processes: int, start_method: str) -> None:
        self.ctx = mp.get_context(start_method)
        self.shared = [_Host(self.ctx, f"scene workers {p}") for p in range(processes)]
        self.workers = workers
        self.placed = 0  #: workers placed so far
        self.sharing = 0  #: of them, placed in a shared host

    def place(self, alone: bool) -> _Host:
        """The host of the next worker: a shared one in turn, or (``alone``: it may run SUMO;
        or a replacement) a new one of its own."""
        k, self.placed = self.placed, self.placed + 1
        if k < self.workers and not alone:
            self.sharing += 1
            return self.shared[(self.sharing - 1) % len(self.shared)]
        return _Host(self.ctx, f"scene worker {k}")


class HostedWorker(WorkerHandle):
    """One scene worker of the ``hosted`` backend (module doc); options ``processes`` (None:
    the usable cores, at most one per worker) and ``start_method`` (``spawn``)."""

    @classmethod
    def prepare(cls, options: dict, workers: int) -> None:
        """Set up the vector env's host processes (called once before its workers start)."""
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else \
            (os.cpu_count() or 1)
        processes = max(1, min(workers, int(options.get("processes") or cores)))
        options["hosts"] = _HostPool(workers, processes, options.get("start_method", "spawn"))

    def start(self) -> None:
        # the scene workers' arguments: (source, config, seed, slots), see make_worker
        alone = len(self.args) >= 2 and runs_sumo(self.args[0], self.args[1])
        self.host = self.options["hosts"].place(alone)
        self.i = self.host.add()
        self.proc = self.host.proc
        self.pid = self.proc.pid
        self.node = "local"
        self.send("hello", (self.factory, self.args), 60.0)

    def send(self, cmd: str, arg: Any, timeout_s: float) -> None:
        self.host.submit(self.i, cmd, arg, timeout_s)

    def recv(self, timeout_s: float) -> Any:
        status, payload = self.host.answer(self.i, timeout_s)
        if status != "ok":
            raise WorkerFailed.of(self.name, payload)
        return payload

    def kill(self) -> None:
        """Stops the whole host process (its other workers are lost with it)."""
        self.host.kill()

    def close(self, timeout_s: float = 5.0) -> None:
        host = self.host
        if host.lost is None:
            try:
                host.submit(self.i, "close", None, timeout_s)
                host.answer(self.i, timeout_s)
            except WorkerLost:
                pass
        host.leave(self.i)
        if not host.live and host.proc is not None:
            host.proc.join(timeout_s)
            host.kill()
