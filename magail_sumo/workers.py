"""Jobs each in a fresh worker process, with a per-job timeout: no wait on a worker is unbounded.

libsumo runs one simulation per process (and has crashed when a second one starts after vehicle
removals), so every SUMO-using job of ``convert``, ``evaluate`` and ``expert`` runs in a process
of its own, started with the ``spawn`` method (the semantics of a pool with
``maxtasksperchild=1``). :func:`run_jobs` runs up to ``workers`` such processes at once and
yields one :class:`JobResult` per job:

* the job returned: ``ok`` is True and ``value`` holds the return value;
* the job raised: ``kind == "error"``, ``reason`` is the exception's one-line message (prefixed
  with its type name unless it is a :class:`~magail_sumo.errors.MagailSumoError`) and
  ``expected`` says whether it was one (a reported bad input rather than a crash or a bug);
* the process died without answering (a crash, ``os._exit``, a signal): ``kind == "died"``
  with the exit code;
* the job ran longer than ``timeout_s`` (a hang, a stopped process, a slow input): the process
  is killed (SIGKILL also ends a stopped process) and ``kind == "timeout"``.

A failed job never stops the others; :func:`run_jobs` itself only raises for bad arguments.
When the caller stops iterating (an exception, Ctrl-C, ``break``) every live worker is killed.
The job function and its argument must be picklable (a module-level function).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import pickle
import sys
import threading
import time
import traceback
from dataclasses import dataclass
from multiprocessing import reduction
from multiprocessing.connection import wait
from multiprocessing.reduction import ForkingPickler
from typing import Any, Callable, Iterable, Iterator

from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import one_line

#: ``progress(phase, done, total)``: told after each unit of a long job (a batch of rollouts, a
#: scene, an env step of a training update); ``magail-sumo`` draws it as a bar on a terminal
Progress = Callable[[str, int, int], None]


def no_progress(phase: str, done: int, total: int) -> None:
    """The :data:`Progress` that shows nothing."""

#: seconds a worker gets to exit after its answer before it is killed
_EXIT_GRACE_S = 5.0


@dataclass
class JobResult:
    """The outcome of one job (see the module doc).

    :param index: position of the job in the input. :param job: the job's argument.
    :param kind: ``"ok"``, ``"error"``, ``"died"`` or ``"timeout"``.
    :param reason: one-line reason of a failure ("" when ok).
    :param expected: the job raised a :class:`~magail_sumo.errors.MagailSumoError`.
    :param seconds: wall time of the job's process (s).
    """

    index: int
    job: Any
    kind: str
    value: Any = None
    reason: str = ""
    expected: bool = False
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return self.kind == "ok"


def _one_line(text: str, limit: int = 400) -> str:
    return one_line(text, limit)


def share_cores() -> None:
    """Run numba's parallel kernels of this thread on one thread (call it in a worker process
    that is one of several sharing the cores).

    A parallel kernel (``prange``: the road-edge distance, the interaction metrics) starts a
    thread per core in every process and waits for all of them at its end; with several
    worker processes on the cores the threads spin against each other and a region waits for
    a thread that is not scheduled: the road-edge rule of a training worker took about 11 ms
    a step on 2 cores instead of well under 1 ms (``docs/results/throughput.md``). The kernels
    compute each item independently, so the results are the same on any number of threads.
    """
    import numba

    if numba.get_num_threads() != 1:
        numba.set_num_threads(1)


def _child(conn, fn: Callable[[Any], Any], jobs, shared: bool = False,
           forked: bool = False) -> None:
    """Worker entry point: receive the job on ``jobs``, run ``fn(job)`` and send ``("ok",
    value)`` or a failure on ``conn``. ``shared``: other workers run beside it
    (:func:`share_cores`). ``forked``: forked from the preload server (:func:`run_jobs`),
    which started earlier: the parent's standard output and error, environment, working folder
    and module path come first on ``jobs`` and replace the server's (as a spawned process
    starts with the parent's)."""
    try:
        if shared:
            share_cores()
        if forked:
            _take_parent_context(jobs)
        arg = pickle.loads(jobs.recv_bytes())
        jobs.close()
        value = fn(arg)
        msg: tuple = ("ok", value)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent
        expected = isinstance(exc, MagailSumoError)
        text = str(exc) or type(exc).__name__
        reason = _one_line(text) if expected else _one_line(f"{type(exc).__name__}: {text}")
        msg = ("error", reason, expected, traceback.format_exc())
    try:
        conn.send(msg)
    except Exception as exc:  # the value does not pickle
        conn.send(("error", _one_line(f"result not transferable: {type(exc).__name__}: {exc}"),
                   False, traceback.format_exc()))
    conn.close()


def _parent_context() -> bytes:
    """This process's environment, working folder and module path, pickled
    (:func:`_take_parent_context`)."""
    return pickle.dumps((dict(os.environ), os.getcwd(), list(sys.path)))


def _take_parent_context(jobs) -> None:
    """In a forked worker: the parent's standard output and error (two descriptors), then its
    environment, working folder and module path (:func:`_send_job`)."""
    for target in (1, 2):
        fd = reduction.recv_handle(jobs)
        os.dup2(fd, target)
        os.close(fd)
    env, cwd, path = pickle.loads(jobs.recv_bytes())
    os.environ.clear()
    os.environ.update(env)
    os.chdir(cwd)
    sys.path[:] = path


def _send_job(conn, data: bytes, context: bytes | None = None, pid: int = 0) -> None:
    """Send a pickled job to a worker (:func:`run_jobs`), after the parent's context for a
    forked one (``context``: :func:`_parent_context`; ``pid``: the worker's); a worker that is
    gone or killed meanwhile ends the send."""
    try:
        if context is not None:
            for fd in (1, 2):
                reduction.send_handle(conn, fd, pid)
            conn.send_bytes(context)
        conn.send_bytes(data)
    except (OSError, EOFError, ValueError):
        pass  # the worker died or was killed: its result says so
    finally:
        conn.close()


def _kill(proc) -> None:
    if proc.is_alive():
        proc.kill()
    proc.join(_EXIT_GRACE_S)


def start_job_server(preload: tuple[str, ...]) -> None:
    """Start the server :func:`run_jobs` forks its job processes from (``preload``: the modules
    it imports, as :func:`run_jobs`' own), now: it imports them in its own process while the
    caller goes on with its work (reading inputs, loading a policy), instead of when the
    first job starts. Does nothing when a server runs already (its list stays)."""
    from multiprocessing import forkserver  # lazy: only callers that fork from a server

    mp.get_context("forkserver").set_forkserver_preload(list(preload))
    forkserver.ensure_running()


def run_jobs(fn: Callable[[Any], Any], jobs: Iterable[Any], *, workers: int = 1,
             timeout_s: float | None = None, ordered: bool = False,
             start_method: str = "spawn", preload: tuple[str, ...] = ()
             ) -> Iterator[JobResult]:
    """Run ``fn(job)`` for every job, each in a fresh process, ``workers`` at a time.

    :param preload: modules the jobs import (e.g. libsumo and the code around it): the jobs'
        processes are then forked from a server process that imported them once
        (multiprocessing's ``forkserver`` with its preload list; a fresh process all the same,
        one job each, without paying the imports per job). Only the first ``run_jobs`` with a
        preload in a process sets the list (the server is started once). Empty: ``start_method``.

    :param timeout_s: seconds a job may run (from its process's start) before its process is
        killed and the job reported as timed out; None: no limit; a callable: each job's own
        limit, ``timeout_s(job)`` (a float or None).
    :param ordered: yield in job order (else as jobs finish).
    :param jobs: consumed lazily, at most ``workers`` ahead of the results.
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    limit_of = timeout_s if callable(timeout_s) else (lambda _job: timeout_s)

    def limit(job) -> float | None:
        value = limit_of(job)
        if value is not None and not value > 0:
            raise ValueError(f"timeout_s must be > 0, got {value}")
        return value

    if not callable(timeout_s):
        limit(None)  # a bad limit fails before any job starts
    forked = bool(preload)
    if forked:
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload(list(preload))
        context = _parent_context()
    else:
        ctx = mp.get_context(start_method)
        context = None
    source = enumerate(jobs)
    running: dict[int, tuple] = {}  # index -> (proc, conn, job, start, limit)
    done: dict[int, JobResult] = {}
    next_out = 0
    exhausted = False
    try:
        while True:
            while not exhausted and len(running) < workers:
                try:
                    k, job = next(source)
                except StopIteration:
                    exhausted = True
                    break
                job_limit = limit(job)
                parent, child = ctx.Pipe(duplex=False)
                # (a socket pair when descriptors go over it: a forked worker's stdio)
                job_in, job_out = ctx.Pipe(duplex=forked)
                # the job (a prepared scene: ~1 MB) goes over its own pipe after the start, from
                # a thread: a worker stopped before it reads blocks that thread, not this loop,
                # and is killed at its timeout like any other (which ends the thread's send)
                proc = ctx.Process(target=_child, args=(child, fn, job_in, workers > 1, forked),
                                   daemon=True, name=f"job-{k}")
                proc.start()
                child.close()
                job_in.close()
                # pickled here: a job that cannot be pickled fails in this process, as before
                data = bytes(ForkingPickler.dumps(job))
                threading.Thread(target=_send_job, args=(job_out, data, context, proc.pid),
                                 daemon=True, name=f"job-{k}-send").start()
                running[k] = (proc, parent, job, time.monotonic(), job_limit)
            if not running:
                break
            now = time.monotonic()
            ends = [s + t for *_, s, t in running.values() if t is not None]
            wait_s = max(0.0, min(ends) - now) if ends else None
            waitables = [c for _, c, *_ in running.values()] + \
                [p.sentinel for p, *_ in running.values()]
            wait(waitables, wait_s)
            now = time.monotonic()
            for k in list(running):
                proc, conn, job, start, job_limit = running[k]
                res = _collect(k, proc, conn, job, start, now, job_limit)
                if res is not None:
                    del running[k]
                    conn.close()
                    done[k] = res
            if ordered:
                while next_out in done:
                    yield done.pop(next_out)
                    next_out += 1
            else:
                for k in sorted(done):
                    yield done.pop(k)
    finally:
        for proc, conn, *_ in running.values():
            _kill(proc)
            conn.close()


def _collect(k: int, proc, conn, job, start: float, now: float, timeout_s: float | None
             ) -> JobResult | None:
    """The job's result when it has one (answered, died or timed out), else None."""
    seconds = now - start
    alive = proc.is_alive()  # before the poll: a worker that exited has written all it sent
    answered = False
    try:
        answered = conn.poll()
    except (OSError, EOFError):
        answered = False
    if answered:
        try:
            msg = conn.recv()
        except (EOFError, OSError, ConnectionError):
            msg = None
        except Exception as exc:  # an answer that does not unpickle here
            msg = ("error", _one_line(f"result not readable: {type(exc).__name__}: {exc}"),
                   False, "")
        if msg is not None:
            proc.join(_EXIT_GRACE_S)
            _kill(proc)
            if msg[0] == "ok":
                return JobResult(k, job, "ok", msg[1], seconds=seconds)
            return JobResult(k, job, "error", reason=msg[1], expected=bool(msg[2]),
                             seconds=seconds)
    if not alive:
        proc.join(_EXIT_GRACE_S)
        code = proc.exitcode
        return JobResult(k, job, "died", reason=f"worker process died (exit code {code})",
                         seconds=seconds)
    if timeout_s is not None and seconds >= timeout_s:
        _kill(proc)
        return JobResult(k, job, "timeout",
                         reason=f"timed out after {timeout_s:g} s (worker killed)",
                         seconds=seconds)
    return None


def run_one(fn: Callable[[Any], Any], job: Any, timeout_s: float | None = None) -> JobResult:
    """:func:`run_jobs` for a single job."""
    return next(run_jobs(fn, [job], workers=1, timeout_s=timeout_s))
