"""Closed-loop comparison with every vehicle controlled: ADE, collision, off-road, speed error.

Each policy drives all route vehicles of each scene from the first log step to the end
(``terminate_on=()``: agents keep driving after an event, so every agent is scored over its
whole recorded life; log background for the rest). Metrics over agents and their valid log
steps: ADE (m, mean distance to the recorded position), collision rate and off-road rate (share
of agents with at least one such event), mean speed error (m/s, |speed − recorded speed|) and
speed bias (m/s, mean of speed − recorded speed: negative = slower than the humans).
Policies: ``constant_velocity`` (zero action: speed and heading held), ``untrained`` (a fresh
policy of the config, observation normaliser fitted on the expert data) and any
``NAME=CHECKPOINT`` (deterministic mean action of the tanh-Gaussian actor). Every
(policy, scene) rollout runs in its own process (libsumo).

    python benchmarks/compare_policies.py --expert out/expert --config configs/magail.yaml \
        --policy bc=runs/bc/checkpoints/latest.pt --policy magail=runs/m/checkpoints/latest.pt [--json]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SCENES = [ROOT / "data" / "womd" / f"{s}.tfrecord"
          for s in ("637f20cafde22ff8", "2831b6fde0420b0d", "850c48d8bbfa008f")]


def rollout(job: tuple) -> dict:
    """One closed-loop episode of one policy on one scene; sums for the metrics."""
    name, policy_state, cfg_dict, spec, seed = job
    warnings.filterwarnings("ignore")
    import torch

    from magail_sumo.config import from_dict
    from magail_sumo.env import EnvConfig, SumoDrivingEnv
    from magail_sumo.env.vec_env import load_spec_scene
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.trainer import make_policy

    torch.set_num_threads(1)
    cfg = from_dict(TrainConfig, cfg_dict)
    policy = None
    if policy_state is not None:
        policy = make_policy(cfg)
        policy.load_state_dict(policy_state)
        policy.set_training_mode(False)
    scene = load_spec_scene(spec)
    env = SumoDrivingEnv(scene, spec.bundle, EnvConfig(
        controlled="all", terminate_on=(), observation=cfg.env.observation,
        limits=cfg.env.limits))
    tr = scene.tracks
    obs, _ = env.reset(seed=seed)
    err_sum = speed_sum = bias_sum = 0.0
    n = 0
    collided: set[str] = set()
    offroad: set[str] = set()
    agents: set[str] = set()
    while env.agents:
        names = list(env.agents)
        if policy is None:
            act = np.zeros((len(names), 2), np.float32)
        else:
            x = np.stack([obs[a] for a in names]).astype(np.float32)
            act, _ = policy.predict(x, deterministic=True)
        obs, _, _, _, infos = env.step(dict(zip(names, act)))
        for a, info in infos.items():
            ev = info.get("events", {})
            if ev.get("collision"):
                collided.add(a)
            if ev.get("off_road"):
                offroad.add(a)
        if env.agents:
            st = env.agent_states()
            t = env.t
            ok = tr.valid[st.rows, t]
            r = st.rows[ok]
            dx = st.state.x[ok] - tr.x[r, t]
            dy = st.state.y[ok] - tr.y[r, t]
            h = tr.heading[r, t]
            v_log = tr.vx[r, t] * np.cos(h) + tr.vy[r, t] * np.sin(h)
            err_sum += float(np.hypot(dx, dy).sum())
            speed_sum += float(np.abs(st.state.speed[ok] - v_log).sum())
            bias_sum += float((st.state.speed[ok] - v_log).sum())
            n += int(ok.sum())
            agents.update(st.names)
    env.close()
    return {"policy": name, "scene": scene.scenario_id, "err": err_sum, "speed": speed_sum,
            "bias": bias_sum, "n": n, "agents": len(agents), "collided": len(collided),
            "offroad": len(offroad)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--expert", required=True, help="expert dir (fits the untrained normaliser)")
    ap.add_argument("--config", default=str(ROOT / "configs" / "magail.yaml"))
    ap.add_argument("--policy", action="append", default=[], metavar="NAME=CHECKPOINT")
    ap.add_argument("--scenes", nargs="*", default=[str(s) for s in SCENES])
    ap.add_argument("--networks", default=str(ROOT / "out" / "networks"))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    import torch

    from magail_sumo.config import load_config, to_dict
    from magail_sumo.env.vec_env import scene_specs
    from magail_sumo.expert import ExpertDataset
    from magail_sumo.sensors.observation import observation_names
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.trainer import load_checkpoint, make_policy

    cfg = load_config(args.config, TrainConfig)
    torch.manual_seed(args.seed)
    untrained = make_policy(cfg)
    expert = ExpertDataset(args.expert, observation_names(cfg.env.observation))
    untrained.obs_normalizer.update(torch.as_tensor(expert.s))
    policies: list[tuple[str, dict | None, dict]] = [
        ("constant_velocity", None, to_dict(cfg)),
        ("untrained", untrained.state_dict(), to_dict(cfg))]
    for item in args.policy:
        name, _, path = item.partition("=")
        state = load_checkpoint(path)
        policies.append((name, state["policy"], state["config"]))
    specs = scene_specs(args.scenes, args.networks)
    jobs = [(n, p, c, s, args.seed) for n, p, c in policies for s in specs]
    with mp.get_context("spawn").Pool(args.workers, maxtasksperchild=1) as pool:
        rows = pool.map(rollout, jobs, chunksize=1)
    table = []
    for name, _, _ in policies:
        rs = [r for r in rows if r["policy"] == name]
        n = sum(r["n"] for r in rs)
        agents = sum(r["agents"] for r in rs)
        table.append({"policy": name, "ade_m": sum(r["err"] for r in rs) / max(n, 1),
                      "collision_rate": sum(r["collided"] for r in rs) / max(agents, 1),
                      "off_road_rate": sum(r["offroad"] for r in rs) / max(agents, 1),
                      "speed_error_mps": sum(r["speed"] for r in rs) / max(n, 1),
                      "speed_bias_mps": sum(r["bias"] for r in rs) / max(n, 1),
                      "agents": agents, "agent_steps": n})
    if args.json:
        print(json.dumps({"per_scene": rows, "table": table}, indent=2))
    else:
        print(f"{'policy':<20}{'ADE m':>9}{'collision':>11}{'off-road':>10}{'speed err':>11}"
              f"{'bias':>7}{'agents':>8}")
        for t in table:
            print(f"{t['policy']:<20}{t['ade_m']:>9.2f}{t['collision_rate']:>11.3f}"
                  f"{t['off_road_rate']:>10.3f}{t['speed_error_mps']:>11.2f}"
                  f"{t['speed_bias_mps']:>7.2f}{t['agents']:>8}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
