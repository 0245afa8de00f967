"""The ``hosted`` worker backend: several scene workers per local process (those that run no
SUMO), the same rollouts as one process per worker, and a lost process's workers replaced with
their episodes replayed."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from conftest import WOMD_DIR, killed_worker_ends_the_env, roll_random
from magail_sumo.env import EnvConfig
from magail_sumo.env.scene_specs import scene_specs
from magail_sumo.env.vec_env import MultiSceneVecEnv
from magail_sumo.training.config import WorkersConfig

CFG = EnvConfig(start_window="random", max_steps=30, sumo_mirror=False,
                terminate_on=("collision", "off_road"))


@pytest.fixture(scope="module")
def specs(bundled_networks):
    files = sorted(WOMD_DIR.glob("*.tfrecord"))
    nets = bundled_networks(*(f.stem for f in files))
    # 5 workers: two scenes played twice (replicas with their own seeds)
    return scene_specs(files, nets) + scene_specs(files[:2], nets)


def test_hosted_workers_give_the_process_backends_rollouts(specs):
    want_venv = MultiSceneVecEnv(specs, CFG, seed=4, backend="process")
    try:
        want = roll_random(want_venv, 90)
        want_state = want_venv.get_state()
        want_reasons = dict(want_venv.end_reasons)
    finally:
        want_venv.close()
    venv = MultiSceneVecEnv(specs, CFG, seed=4, backend="hosted",
                            backend_options={"processes": 2})
    try:
        pids = {h.pid for h in venv._handles}
        assert len(pids) == 2 and len(venv._handles) == 5
        got = roll_random(venv, 90)
        assert venv.episodes >= 5 and dict(venv.end_reasons) == want_reasons
        state = venv.get_state()
    finally:
        venv.close()
    for a, b in zip(want, got):
        np.testing.assert_array_equal(a, b)
    assert [(e, len(a)) for e, a in state] == [(e, len(a)) for e, a in want_state]
    assert not any(h.proc.is_alive() for h in venv._handles)


@pytest.mark.parametrize("how", ["kill", "stop"])
def test_a_lost_host_process_is_replaced_exactly(specs, how):
    want_venv = MultiSceneVecEnv(specs, CFG, seed=6, backend="hosted",
                                 backend_options={"processes": 2})
    try:
        want = roll_random(want_venv, 40)
    finally:
        want_venv.close()

    def fault(t, v):
        if t == 17:  # mid-episode
            os.kill(v._handles[1].pid, signal.SIGKILL if how == "kill" else signal.SIGSTOP)
            v.timeout_s = 4.0

    logs: list[str] = []
    venv = MultiSceneVecEnv(specs, CFG, seed=6, backend="hosted",
                            backend_options={"processes": 2}, max_restarts=1, log=logs.append)
    try:
        host = venv._handles[1].pid
        lost = [k for k, h in enumerate(venv._handles) if h.pid == host]
        got = roll_random(venv, 40, hook=fault)
        # every worker of the lost process was replaced, each in a process of its own
        assert venv.restarts == len(lost) == 2
        assert len({venv._handles[k].pid for k in lost}) == 2 and host not in \
            {h.pid for h in venv._handles}
    finally:
        venv.close()
    for a, b in zip(want, got):
        np.testing.assert_array_equal(a, b)
    assert len([m for m in logs if "replaced" in m and "replayed" in m]) == 2
    # no replacement allowed: one line naming the cause
    killed_worker_ends_the_env(MultiSceneVecEnv(specs, CFG, seed=6, backend="hosted",
                                                max_restarts=0))


def test_workers_that_run_sumo_get_a_process_each(specs):
    """libsumo runs one simulation per process: with the SUMO mirror every worker is alone in
    its process, and the rollouts are the process backend's."""
    cfg = EnvConfig(controlled=3, max_steps=12)  # the SUMO mirror on (the default)
    want_venv = MultiSceneVecEnv(specs[:3], cfg, seed=2, backend="process")
    try:
        want = roll_random(want_venv, 20)
    finally:
        want_venv.close()
    venv = MultiSceneVecEnv(specs[:3], cfg, seed=2, backend="hosted",
                            backend_options={"processes": 2})
    try:
        assert len({h.pid for h in venv._handles}) == 3
        got = roll_random(venv, 20)
    finally:
        venv.close()
    for a, b in zip(want, got):
        np.testing.assert_array_equal(a, b)


def test_training_config_takes_the_hosted_backend():
    assert WorkersConfig(backend="hosted").backend == "hosted"
    with pytest.raises(Exception, match="'process', 'hosted' or 'ray'"):
        WorkersConfig(backend="threads")
