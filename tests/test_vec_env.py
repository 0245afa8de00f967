"""MultiSceneVecEnv: agents as SB3 slots over scenes in worker processes."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR
from magail_sumo.env import EnvConfig
from magail_sumo.env.vec_env import MultiSceneVecEnv, VecEnvWorkerError
from magail_sumo.env.scene_specs import scene_specs


@pytest.fixture(scope="module")
def specs(bundled_networks):
    nets = bundled_networks("850c48d8bbfa008f")
    return scene_specs([WOMD_DIR / "850c48d8bbfa008f.tfrecord"], nets) + \
        scene_specs([WOMD_DIR / "637f20cafde22ff8.tfrecord"], ROOT / "networks",
                    convert_missing=False)


@pytest.mark.sumo
def test_slots_masks_and_dones(specs):
    venv = MultiSceneVecEnv(specs, EnvConfig(controlled=6, max_steps=30), seed=1)
    try:
        assert venv.num_envs == sum(venv.slots) and venv.slots[0] >= 1
        obs = venv.reset()
        assert obs.shape == (venv.num_envs, venv.obs_dim) and obs.dtype == np.float32
        assert np.all(obs[~venv.slot_active] == 0)
        assert [i["slot_active"] for i in venv.reset_infos] == venv.slot_active.tolist()
        seen_done = False
        for _ in range(40):
            before = venv.slot_active.copy()
            obs, rew, dones, infos = venv.step(np.random.default_rng(0).uniform(
                -1, 1, (venv.num_envs, 2)))
            assert np.array_equal(venv.prev_slot_active, before)
            assert np.all(rew == 0) and np.all(obs[~venv.slot_active] == 0)
            for i, info in enumerate(infos):
                assert info["slot_active"] == venv.slot_active[i]
                if "terminal_observation" in info:
                    assert dones[i] and before[i] and info["reason"]
                    seen_done = True
                # a free slot given to a new agent starts a new episode of that slot
                if venv.slot_active[i] and not before[i]:
                    assert dones[i]
        assert seen_done and venv.episodes >= 1 and venv.agent_steps > 0
    finally:
        venv.close()


@pytest.mark.sumo
def test_state_replay_restores_exactly(specs):
    cfg = EnvConfig(controlled=5, max_steps=25)
    venv = MultiSceneVecEnv(specs, cfg, seed=3)
    rng = np.random.default_rng(0)
    acts = rng.uniform(-1, 1, (35, venv.num_envs, 2)).astype(np.float32)
    try:
        venv.reset()
        for a in acts[:20]:
            venv.step(a)
        state = venv.get_state()
        tail = [venv.step(a)[0] for a in acts[20:]]
    finally:
        venv.close()
    other = MultiSceneVecEnv(specs, cfg, seed=3)
    try:
        other.set_state(state)
        again = [other.step(a)[0] for a in acts[20:]]
    finally:
        other.close()
    for x, y in zip(tail, again):
        np.testing.assert_array_equal(x, y)


@pytest.mark.sumo
def test_dead_or_hung_worker_raises(specs):
    venv = MultiSceneVecEnv(specs[:1], EnvConfig(controlled=3, max_steps=10))
    venv.reset()
    venv.timeout_s = 3.0  # after start-up, which may take longer on a busy machine
    os.kill(venv._procs[0].pid, signal.SIGKILL)
    with pytest.raises(VecEnvWorkerError, match="died"):
        venv.step(np.zeros((venv.num_envs, 2)))
    venv.close()
    venv = MultiSceneVecEnv(specs[:1], EnvConfig(controlled=3, max_steps=10))
    venv.reset()
    venv.timeout_s = 2.0
    os.kill(venv._procs[0].pid, signal.SIGSTOP)
    with pytest.raises(VecEnvWorkerError, match="did not answer"):
        venv.step(np.zeros((venv.num_envs, 2)))
    venv.close()
    assert not venv._procs[0].is_alive()


def test_place_workers_balances_cores():
    from magail_sumo.env.vec_env import place_workers

    # the big scene keeps a core to itself; the two small ones share the other
    assert place_workers([50.0, 21.0, 13.0], [0, 1]) == [{0}, {1}, {1}]
    assert place_workers([5.0, 5.0], [2, 3, 4]) == [{2}, {3}]
    loads = [30.0, 28.0, 20.0, 12.0, 10.0]
    cpus = place_workers(loads, [0, 1])
    per_core = [sum(w for w, c in zip(loads, cpus) if c == {k}) for k in (0, 1)]
    assert abs(per_core[0] - per_core[1]) <= 12.0 and all(len(c) == 1 for c in cpus)


@pytest.mark.sumo
def test_workers_are_pinned_when_asked(specs):
    if not hasattr(os, "sched_getaffinity"):
        pytest.skip("no CPU affinity on this platform")
    venv = MultiSceneVecEnv(specs, EnvConfig(controlled=3, max_steps=5), pin_workers=True)
    try:
        for proc, cpus in zip(venv._procs, venv.worker_cpus):
            assert os.sched_getaffinity(proc.pid) == cpus and len(cpus) == 1
    finally:
        venv.close()
    venv = MultiSceneVecEnv(specs[:1], EnvConfig(controlled=3, max_steps=5), pin_workers=False)
    try:
        assert venv.worker_cpus == [set()]
        assert os.sched_getaffinity(venv._procs[0].pid) == os.sched_getaffinity(0)
    finally:
        venv.close()


class _Echo:
    """A trivial worker object for transport tests (no SUMO)."""

    def hello(self) -> dict:
        return {"pid": os.getpid()}

    def handle(self, cmd, arg):
        return os.sched_getscheduler(0) if cmd == "policy" else arg

    def close(self) -> None:
        pass


def _echo() -> _Echo:
    return _Echo()


def test_process_workers_run_as_batch_tasks():
    """Process workers run under SCHED_BATCH (they never preempt the trainer's sends)."""
    if not hasattr(os, "SCHED_BATCH"):
        pytest.skip("no SCHED_BATCH on this platform")
    from magail_sumo.env.transport import ProcessWorker

    w = ProcessWorker("echo", _echo, ())
    w.start()
    try:
        assert w.recv(30.0)["pid"] == w.pid
        w.send("policy", None, 5.0)
        assert w.recv(30.0) == os.SCHED_BATCH
        w.send("echo", [1, 2], 5.0)
        assert w.recv(30.0) == [1, 2]
    finally:
        w.close()
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the trainer keeps the default


_WORKER_IMPORTS = """
import sys
from magail_sumo.env import EnvConfig
from magail_sumo.env.slot_worker import SceneSpec, make_worker
w = make_worker(SceneSpec(*sys.argv[1:4]), EnvConfig(controlled=3, max_steps=5), 0, None)
packet = w.reset()
packet = w.step(packet["obs"][:, :2] * 0)
assert packet["agent_steps"] > 0
w.close()
print(sorted(m for m in ("torch", "stable_baselines3") if m in sys.modules))
"""


@pytest.mark.sumo
def test_scene_worker_holds_no_learner_imports(specs):
    """A scene worker builds, resets and steps its scene without importing torch or SB3
    (about 0.5 GiB per worker process): what the process and Ray backends import."""
    import subprocess
    import sys

    spec = specs[1]
    out = subprocess.run([sys.executable, "-c", _WORKER_IMPORTS, spec.scene_file, spec.bundle,
                          spec.scenario_id], capture_output=True, text=True, cwd=ROOT,
                         timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "[]"


# ------------------------------------------------------------------------------- every wait bounded
SID = "850c48d8bbfa008f"  # the smallest bundled scene
SCENE = WOMD_DIR / f"{SID}.tfrecord"


@pytest.mark.sumo
def test_vec_env_large_request_to_a_stopped_worker_times_out(bundled_networks):
    from magail_sumo.env import EnvConfig
    from magail_sumo.env.vec_env import MultiSceneVecEnv, SceneSpec, VecEnvWorkerError

    spec = SceneSpec(str(SCENE), str(bundled_networks(SID) / SID), SID)
    venv = MultiSceneVecEnv([spec], EnvConfig(controlled=3, max_steps=10), timeout_s=120.0)
    try:
        venv.reset()
        venv.timeout_s = 3.0
        os.kill(venv._procs[0].pid, signal.SIGSTOP)
        # distinct arrays (pickle would share one): far beyond a pipe's 64 KiB
        replay = [np.zeros((venv.num_envs, 2), np.float32) for _ in range(20_000)]
        clock = time.monotonic()
        with pytest.raises(VecEnvWorkerError, match="did not read its request within 3 s"):
            venv.set_state([(0, replay)])
        assert time.monotonic() - clock < 120  # generous: a stopped worker never reads
        assert not venv._procs[0].is_alive()
    finally:
        venv.close()
