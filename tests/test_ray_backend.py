"""Ray backend of the scene workers on a real two-node Ray cluster on this machine: actors on
both nodes, the same rollouts as the process backend, training with an actor killed
mid-rollout, and an unreachable cluster refused in one line."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest

from conftest import WOMD_DIR, roll_random

ray = pytest.importorskip("ray")

from converters.scene_files import RecordRef  # noqa: E402
from magail_sumo.config import from_dict  # noqa: E402
from magail_sumo.env.config import EnvConfig  # noqa: E402
from magail_sumo.env.vec_env import pool_vec_env  # noqa: E402
from magail_sumo.env.scene_specs import scene_specs  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SCENES = [WOMD_DIR / "850c48d8bbfa008f.tfrecord",
          ROOT / "data" / "scenarionet" / "250011f460de6135.pkl",
          ROOT / "data" / "scenarionet" / "53e9adfdac0eb822.pkl"]
CFG = EnvConfig(start_window="random", max_steps=15, controlled=6)

pytestmark = pytest.mark.sumo


def test_unreachable_cluster_is_one_line(tmp_path, capsys, bundled_networks):
    from magail_sumo.cli.main import main
    from magail_sumo.env.ray_workers import RayUnavailable, init_ray

    if ray.is_initialized():
        pytest.skip("Ray already initialised in this process")
    with pytest.raises(RayUnavailable, match=r"workers\.ray\.address 127\.0\.0\.1:9: no Ray "
                                             r"cluster answers there"):
        init_ray("127.0.0.1:9")
    from magail_sumo.expert import record_expert

    nets = bundled_networks(SCENES[0].stem)
    record_expert(scene_specs([SCENES[0]], nets), tmp_path / "expert")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"expert_dir: {tmp_path / 'expert'}\nscenes:\n  files: ['{SCENES[0]}']\n"
                   f"  networks: {nets}\nworkers:\n  backend: ray\n  ray:\n"
                   "    address: 127.0.0.1:9\n")
    assert main(["train", "--config", str(cfg), "--run-dir", str(tmp_path / "run")]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: magail-sumo train: workers.ray.address "
                                               "127.0.0.1:9: no Ray cluster answers there")
    assert not ray.is_initialized()


@pytest.fixture(scope="module")
def cluster():
    from ray.cluster_utils import Cluster

    if ray.is_initialized():
        ray.shutdown()
    c = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    c.add_node(num_cpus=1)
    c.wait_for_nodes()
    ray.init(address=c.address, include_dashboard=False, log_to_driver=False,
             logging_level="ERROR")
    yield c
    ray.shutdown()
    c.shutdown()


def test_ray_actors_on_both_nodes_give_the_process_rollouts(cluster, bundled_networks):
    refs = [RecordRef(str(f)) for f in SCENES]
    nets = bundled_networks(*(f.stem for f in SCENES))
    want_env = pool_vec_env(refs, nets, 2, CFG, seed=5)
    try:
        want = roll_random(want_env, 40, seed=1)
    finally:
        want_env.close()
    venv = pool_vec_env(refs, nets, 2, CFG, seed=5, backend="ray",
                        backend_options={"address": cluster.address})
    try:
        got = roll_random(venv, 40, seed=1)
        nodes = {h.node for h in venv._handles}
    finally:
        venv.close()
    assert len(nodes) == 2  # one actor per node (SPREAD, one CPU each)
    assert {n["NodeID"] for n in ray.nodes() if n["Alive"]} == nodes
    for a, b in zip(want, got):
        np.testing.assert_array_equal(a, b)

    # a hung actor (its SUMO stopped) times out, is replaced, and the rollout is unchanged
    def hang(t, v):
        if t == 17:
            os.kill(v._handles[1].pid, signal.SIGSTOP)
            v.timeout_s = 4.0

    logs: list[str] = []
    venv = pool_vec_env(refs, nets, 2, CFG, seed=5, backend="ray",
                        backend_options={"address": cluster.address}, max_restarts=1,
                        log=logs.append)
    try:
        got = roll_random(venv, 40, seed=1, hook=hang)
        assert venv.restarts == 1
    finally:
        venv.close()
    for a, b in zip(want, got):
        np.testing.assert_array_equal(a, b)
    assert any("Ray actor did not answer within 4 s" in m and "replaced" in m for m in logs)


def test_ray_training_goes_on_past_a_killed_actor(cluster, tmp_path, bundled_networks):
    from magail_sumo.expert import ExpertDataset, record_expert
    from magail_sumo.sensors.observation import observation_names
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.trainer import GailRun

    nets = bundled_networks(*(f.stem for f in SCENES))  # the pool's scenes, converted
    record_expert(scene_specs([SCENES[0]], nets), tmp_path / "expert")
    cfg = from_dict(TrainConfig, {
        "seed": 2, "expert_dir": str(tmp_path / "expert"),
        "env": {"max_steps": 15, "start_window": "random", "controlled": 6},
        "scenes": {"files": [str(s) for s in SCENES], "networks": str(nets),
                   "worker_timeout_s": 60.0},
        "workers": {"count": 2, "backend": "ray", "ray": {"address": cluster.address}},
        "policy": {"actor_hidden": [16, 16], "critic_hidden": [16, 16]},
        "ppo": {"n_steps": 16, "batch_size": 16, "n_epochs": 1},
        "discriminator": {"kind": "mlp", "epochs": 1, "batch_size": 16}})
    expert = ExpertDataset(cfg.expert_dir, observation_names(cfg.env.observation))
    logs: list[str] = []
    run = GailRun(cfg, expert, log=logs.append)
    try:
        venv = run.venv
        assert len({h.node for h in venv._handles}) == 2
        step_wait, calls = venv.step_wait, [0]

        def killing_step_wait():
            calls[0] += 1
            if calls[0] == 7:  # mid-rollout of the first update
                ray.kill(venv._handles[0].actor, no_restart=True)
            return step_wait()

        venv.step_wait = killing_step_wait
        run.run_update()
        run.run_update()
        assert run.update == 2 and venv.restarts == 1
        assert calls[0] == 2 * cfg.ppo.n_steps
    finally:
        run.close()
    assert any(m.startswith("worker 0 ") and "Ray actor died" in m and "replaced" in m
               for m in logs), logs
    assert any(m.startswith("scene pool: 3 scene(s) over 2 ray worker(s)") for m in logs)


def test_too_few_cluster_cpus_is_one_line(cluster, tmp_path):
    from magail_sumo.env.ray_workers import RayUnavailable

    refs = [RecordRef(str(f)) for f in SCENES]
    with pytest.raises(RayUnavailable, match=r"the Ray cluster has 2 CPUs; 3 scene workers of "
                                             r"1 CPU each need 3"):
        pool_vec_env(refs, tmp_path / "nets", 3, CFG, backend="ray",
                     backend_options={"address": cluster.address})
