"""Ray backend of the scene workers on a real two-node Ray cluster on this machine: actors on
both nodes, the same rollouts as the process backend, training with an actor killed
mid-rollout, an unreachable cluster or a service that is not Ray refused in one line, and a
local Ray whose sockets all listen on loopback."""

from __future__ import annotations

import ipaddress
import os
import signal
import socket
import subprocess
import sys
import threading
import time
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


def _listeners(pids: set[int]) -> list[tuple[str, int, int]]:
    """(address, port, pid) of every listening TCP socket (IPv4 and IPv6) held by ``pids``,
    read from /proc (an IPv4-mapped IPv6 address is given as IPv4)."""
    inodes = {}
    for table, v6 in (("/proc/net/tcp", False), ("/proc/net/tcp6", True)):
        for line in Path(table).read_text().splitlines()[1:]:
            f = line.split()
            if f[3] != "0A":  # TCP_LISTEN
                continue
            hexip, hexport = f[1].split(":")
            raw = bytes.fromhex(hexip)
            raw = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))
            ip = ipaddress.ip_address(raw)
            if v6 and ip.ipv4_mapped is not None:
                ip = ip.ipv4_mapped
            inodes[f[9]] = (str(ip), int(hexport, 16))
    found = []
    for pid in pids:
        try:
            fds = os.listdir(f"/proc/{pid}/fd")
        except OSError:
            continue
        for fd in fds:
            try:
                target = os.readlink(f"/proc/{pid}/fd/{fd}")
            except OSError:
                continue
            if target.startswith("socket:[") and target[8:-1] in inodes:
                found.append((*inodes[target[8:-1]], pid))
    return found


def _tree(root: int) -> set[int]:
    """``root`` and all its live descendants."""
    children: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                ppid = int(Path(f"/proc/{d}/stat").read_text().rpartition(")")[2].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d))
    tree, todo = set(), [root]
    while todo:
        pid = todo.pop()
        tree.add(pid)
        todo.extend(children.get(pid, []))
    return tree


_LOCAL_RAY = """
import sys
import ray
from magail_sumo.env.ray_workers import init_ray
init_ray(None, 1)
@ray.remote(num_cpus=1)
class Probe:
    def ping(self):
        return 1
p = Probe.remote()
assert ray.get(p.ping.remote(), timeout=60) == 1
print("ready", flush=True)
sys.stdin.readline()
ray.shutdown()
"""


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="needs Linux /proc")
def test_local_ray_listens_on_loopback_only():
    """Every listening socket of a local Ray started by init_ray (driver, GCS, raylet,
    runtime-env agent, a worker with an actor) is on 127.0.0.1 or ::1."""
    proc = subprocess.Popen([sys.executable, "-c", _LOCAL_RAY], cwd=ROOT, text=True,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL)
    watchdog = threading.Timer(180, proc.kill)
    watchdog.start()
    try:
        assert proc.stdout.readline().strip() == "ready", "the local Ray did not start"
        found = _listeners(_tree(proc.pid))
        owners = {Path(f"/proc/{pid}/comm").read_text().strip() for _, _, pid in found}
        assert {"gcs_server", "raylet"} <= owners, found
        exposed = [(ip, port, Path(f"/proc/{pid}/comm").read_text().strip())
                   for ip, port, pid in found if not ipaddress.ip_address(ip).is_loopback]
        assert not exposed, f"Ray sockets listening beyond loopback: {exposed}"
    finally:
        try:
            proc.stdin.close()
            proc.wait(timeout=60)
        except (OSError, subprocess.TimeoutExpired):
            proc.kill()
        watchdog.cancel()


def _tcp_service(mode: str) -> tuple[socket.socket, int]:
    """A plain TCP service on 127.0.0.1 that is not Ray: ``silent`` accepts and never
    answers; ``redis`` answers any bytes with a Redis error line."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(16)
    conns: list[socket.socket] = []

    def serve():
        while True:
            try:
                conn, _ = server.accept()
            except OSError:  # closed: the test is over
                break
            conns.append(conn)
            if mode == "redis":
                try:
                    if conn.recv(4096):
                        conn.sendall(b"-ERR unknown command\r\n")
                except OSError:
                    pass
        for c in conns:
            c.close()

    threading.Thread(target=serve, daemon=True).start()
    return server, server.getsockname()[1]


_CONNECT = """
import sys
from magail_sumo.env.ray_workers import RayUnavailable, init_ray
try:
    init_ray(sys.argv[1])
except RayUnavailable as exc:
    print(exc, file=sys.stderr)
    sys.exit(3)
"""


@pytest.mark.parametrize("mode", ["silent", "redis"])
def test_a_service_that_is_not_ray_is_refused_in_one_line(mode):
    server, port = _tcp_service(mode)
    address = f"127.0.0.1:{port}"
    t0 = time.monotonic()
    try:
        done = subprocess.run([sys.executable, "-c", _CONNECT, address], cwd=ROOT, text=True,
                              capture_output=True, timeout=20, check=False)
    except subprocess.TimeoutExpired:
        pytest.fail(f"ray address {address} ({mode} non-Ray service) still pending after 20 s")
    finally:
        server.close()
    assert time.monotonic() - t0 < 20
    err = done.stderr.strip().splitlines()
    assert done.returncode == 3 and len(err) == 1, done.stderr
    assert err[0].startswith(f"workers.ray.address {address}: the service there is not a Ray "
                             "cluster ("), err[0]


def test_node_ip_must_be_an_address():
    from magail_sumo.config import ConfigError
    from magail_sumo.training.config import RayConfig

    assert from_dict(RayConfig, {"node_ip": "10.1.2.3"}).node_ip == "10.1.2.3"
    assert from_dict(RayConfig, {}).node_ip is None
    for bad in ("0.0.0.0", "::", "head-node", ""):
        with pytest.raises(ConfigError, match=r"node_ip: must be an IP address of this machine"):
            from_dict(RayConfig, {"node_ip": bad})


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


def test_a_ray_head_passes_the_probe_and_a_driver_joins(cluster):
    from magail_sumo.env.ray_workers import _probe_head

    assert _probe_head(cluster.address) is None
    node = next(n for n in ray.nodes() if n["Alive"])  # a raylet: gRPC, but not the head
    why = _probe_head(f"{node['NodeManagerAddress']}:{node['NodeManagerPort']}")
    assert why is not None and why.startswith("it is a gRPC service without a Ray head's")
    join = ("import sys, ray\nfrom magail_sumo.env.ray_workers import init_ray\n"
            "init_ray(sys.argv[1])\nprint(ray.cluster_resources()['CPU'])\nray.shutdown()\n")
    done = subprocess.run([sys.executable, "-c", join, cluster.address], cwd=ROOT, text=True,
                          capture_output=True, timeout=120, check=False)
    assert done.returncode == 0 and done.stdout.split() == ["2.0"], done.stderr[-2000:]


def test_too_few_cluster_cpus_is_one_line(cluster, tmp_path):
    from magail_sumo.env.ray_workers import RayUnavailable

    refs = [RecordRef(str(f)) for f in SCENES]
    with pytest.raises(RayUnavailable, match=r"the Ray cluster has 2 CPUs; 3 scene workers of "
                                             r"1 CPU each need 3"):
        pool_vec_env(refs, tmp_path / "nets", 3, CFG, backend="ray",
                     backend_options={"address": cluster.address})
