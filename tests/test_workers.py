"""The job pool (``magail_sumo.workers``): a job that returns, raises, exits, is killed, hangs
or stops itself ends as one result with a one-line reason while the other jobs finish; real
worker processes. The job function is module-level so that spawned workers can import it."""

from __future__ import annotations

import os
import signal
import time

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
