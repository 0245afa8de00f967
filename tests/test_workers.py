"""The job pool (``magail_sumo.workers``): a job that returns, raises, exits, is killed, hangs
or stops itself ends as one result with a one-line reason while the other jobs finish; real
worker processes. The job function is module-level so that spawned workers can import it."""

from __future__ import annotations

import os
import signal
import time

import pytest

from magail_sumo.workers import run_jobs


def fault_job(job: tuple) -> object:
    """A job that returns, exits, is killed, hangs, stops itself or raises."""
    what, value = job
    if what == "exit":
        os._exit(3)
    if what == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    if what == "sleep":
        time.sleep(600)
    if what == "stop":
        os.kill(os.getpid(), signal.SIGSTOP)
    if what == "raise":
        raise ValueError(f"bad job\nsecond line {value}")
    return value * 2


def test_pool_reports_dead_and_stuck_workers_and_finishes_the_others():
    jobs = [("ok", 1), ("exit", 0), ("kill", 0), ("sleep", 0), ("stop", 0), ("raise", 7),
            ("ok", 2)]
    clock = time.monotonic()
    res = list(run_jobs(fault_job, jobs, workers=3, timeout_s=15.0, ordered=True))
    assert time.monotonic() - clock < 300  # generous: the hung job sleeps 600 s
    assert [r.index for r in res] == list(range(len(jobs)))
    kinds = [r.kind for r in res]
    assert kinds == ["ok", "died", "died", "timeout", "timeout", "error", "ok"]
    assert [res[0].value, res[-1].value] == [2, 4]
    assert "exit code 3" in res[1].reason and "exit code -9" in res[2].reason
    assert res[3].reason == "timed out after 15 s (worker killed)"
    assert res[5].reason == "ValueError: bad job second line 7" and not res[5].expected
    assert all("\n" not in r.reason for r in res)


def test_each_job_may_have_its_own_time_limit():
    """``timeout_s`` as a callable: every job runs under its own limit (evaluation gives a
    process running several batches in turn the sum of theirs)."""
    jobs = [("sleep", 0), ("ok", 3), ("sleep", 1)]
    limits = {0: 2.0, 1: 6.0}
    clock = time.monotonic()
    res = list(run_jobs(fault_job, jobs, workers=3, ordered=True,
                        timeout_s=lambda job: limits.get(job[1])))
    assert time.monotonic() - clock < 60
    assert [r.kind for r in res] == ["timeout", "ok", "timeout"]
    assert res[0].reason == "timed out after 2 s (worker killed)"
    assert res[2].reason == "timed out after 6 s (worker killed)"
    with pytest.raises(ValueError, match="timeout_s must be > 0"):
        list(run_jobs(fault_job, [("ok", 1)], timeout_s=lambda job: 0.0))


def _children() -> set[int]:
    out = set()
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                if int(open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[1]) == \
                        os.getpid():
                    out.add(int(pid))
            except (OSError, IndexError, ValueError):
                pass
    return out


def _nap(x):
    time.sleep(30)


def test_a_worker_stopped_while_it_starts_is_killed_at_its_timeout():
    """A worker stopped (SIGSTOP) before it read its job (a prepared scene is ~1 MB, more than
    a pipe holds) used to block the parent inside Process.start(), past every timeout; the job
    now goes over its own pipe from a thread, and the stopped worker is killed at its
    timeout."""
    import signal
    import threading

    import numpy as np

    from magail_sumo.workers import run_jobs

    before = _children()
    stop = threading.Event()

    def stopper():
        while not stop.is_set():
            for pid in _children() - before:
                try:
                    os.kill(pid, signal.SIGSTOP)
                except OSError:
                    pass
            time.sleep(0.02)

    threading.Thread(target=stopper, daemon=True).start()
    t0 = time.monotonic()
    big = np.zeros(2_000_000)  # 16 MB
    try:
        kinds = [r.kind for r in run_jobs(_nap, [big, big], workers=2, timeout_s=6)]
    finally:
        stop.set()
    assert kinds == ["timeout", "timeout"] and time.monotonic() - t0 < 30


def test_a_worker_error_is_one_line_its_traceback_kept_for_debug(capsys):
    """A scene worker's error reaches the user as its one line; the worker's traceback is kept
    on the exception and printed by the CLI only with --debug."""
    import pytest

    from magail_sumo.cli.main import _worker_tracebacks
    from magail_sumo.env.transport import WorkerFailed, serve

    def broken():
        raise RuntimeError("SUMO failed to start: Process Error")

    status, payload = serve(broken, (), "hello", None, {})
    assert status == "error"
    exc = WorkerFailed.of("scene a#0", payload)
    assert str(exc) == "scene a#0: worker failed: RuntimeError: SUMO failed to start: Process Error"
    assert "Traceback (most recent call last)" in exc.worker_traceback
    with pytest.raises(RuntimeError) as info:
        try:
            raise exc
        except WorkerFailed:
            raise RuntimeError("every scene of this worker failed")
    _worker_tracebacks(info.value)
    assert "in the worker:\nTraceback" in capsys.readouterr().err


def _kernel_threads(_job) -> int:
    import numba

    return numba.get_num_threads()


class _ThreadsWorker:
    def hello(self) -> int:
        return _kernel_threads(None)

    def handle(self, cmd, arg) -> int:
        return _kernel_threads(None)


def test_workers_side_by_side_run_numba_kernels_on_one_thread():
    """Several job processes, and every scene worker, run numba's parallel kernels on one
    thread (share_cores); a job alone keeps numba's default."""
    import numba

    from magail_sumo.env.transport import serve

    side_by_side = [r.value for r in run_jobs(_kernel_threads, [0, 1], workers=2)]
    alone = next(run_jobs(_kernel_threads, [0], workers=1)).value
    assert side_by_side == [1, 1]
    assert alone == numba.config.NUMBA_NUM_THREADS
    default = numba.get_num_threads()
    try:
        state: dict = {}
        assert serve(_ThreadsWorker, (), "hello", None, state) == ("ok", 1)
        assert serve(_ThreadsWorker, (), "step", None, state) == ("ok", 1)
    finally:
        numba.set_num_threads(default)


def _context_job(tag: str) -> tuple:
    """A job telling what its process sees: an env variable, its folder, whether a preloaded
    module is imported already, and a line on its standard error."""
    import sys

    print(f"worker line {tag}", file=sys.stderr, flush=True)
    return os.environ.get("MAGAIL_SUMO_TEST_TAG"), os.getcwd(), "colorsys" in sys.modules


def test_preloaded_workers_run_with_the_parents_current_context(tmp_path, monkeypatch, capfd):
    """Workers forked from the preload server (started by the first call) see the parent's
    environment, folder and standard error as they are at each call, not as they were when
    the server started; the faults are reported as with spawned workers."""
    monkeypatch.setenv("MAGAIL_SUMO_TEST_TAG", "first")
    res = list(run_jobs(_context_job, ["a"], preload=("colorsys",)))
    assert res[0].ok and res[0].value[0] == "first" and res[0].value[2]
    (tmp_path / "later").mkdir()
    monkeypatch.chdir(tmp_path / "later")
    monkeypatch.setenv("MAGAIL_SUMO_TEST_TAG", "second")
    capfd.readouterr()
    res = list(run_jobs(_context_job, ["b", "c"], workers=2, preload=("colorsys",),
                        ordered=True))
    assert [r.value[:2] for r in res] == [("second", str(tmp_path / "later"))] * 2
    err = capfd.readouterr().err
    assert "worker line b" in err and "worker line c" in err
    faults = list(run_jobs(fault_job, [("exit", 0), ("raise", 1), ("sleep", 0), ("ok", 4)],
                           workers=2, timeout_s=10.0, ordered=True, preload=("colorsys",)))
    assert [r.kind for r in faults] == ["died", "error", "timeout", "ok"]
    assert faults[-1].value == 8


#: a fresh interpreter: start the job server with one module list, then run a job asking for
#: another (argv: the folder of the probe module)
_EARLY_SERVER = """
import sys
sys.path.insert(0, sys.argv[1])
import probe_mod
from magail_sumo.workers import run_jobs, start_job_server
start_job_server(("colorsys",))
res = list(run_jobs(probe_mod.loaded, ["colorsys", "wave"], preload=("wave",), workers=2,
                    ordered=True))
print(" ".join(str(r.ok and r.value) for r in res), "colorsys" in sys.modules)
"""


def test_a_job_server_started_early_keeps_its_modules_and_serves_the_jobs(tmp_path):
    """start_job_server: the server imports its list in its own process (the caller never
    does) and later jobs fork from it, whatever preload they name."""
    import subprocess
    import sys

    (tmp_path / "probe_mod.py").write_text(
        "import sys\n\ndef loaded(name):\n    return name in sys.modules\n")
    out = subprocess.run([sys.executable, "-c", _EARLY_SERVER, str(tmp_path)],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["True", "False", "False"]
