"""Training throughput: the whole MAGAIL loop and the discriminator alone.

* ``agent_steps_per_s``: agent-steps (active slot-steps) per second of complete PPO updates —
  rollout in the scene workers with imitation rewards, discriminator training, PPO epochs —
  with a config (default ``configs/experiments/womd3/magail.yaml``) on its real scenes; the
  first update is excluded as warm-up, and a config's behavioural-cloning initialisation runs
  first, untimed, as in training (a BC policy keeps more agents alive per step than an untrained one);
* ``disc_tokens_per_s``: vehicle tokens per second through the discriminator loss forward +
  backward (GAIL BCE + gradient penalty), expert and policy tokens counted, at the config's
  transformer size and batch.

CPU always, GPU too when ``torch.cuda.is_available()``. ``--config`` may be repeated;
``--workers 1,2`` measures each number of scene workers (``workers.count``; default: the
config's), ``--scenes-per-env 1,5`` each number of recorded scenes a worker steps as one tiled
env (``workers.scenes_per_env``), ``--backend process,hosted,ray`` each worker backend — Ray on a local cluster of
``--ray-nodes`` nodes started by the script (``ray.cluster_utils.Cluster``, the machine's cores
shared out over the nodes; actors spread over them) — and ``--repeats R`` repeats every
measurement and reports the median (``agent_steps_per_s_runs`` lists the runs). Every row has
``device``, ``config``, ``backend``, ``workers``, ``scenes_per_env``, ``nodes``, ``agent_steps_per_s``,
``disc_tokens_per_s`` and, when the same config/backend/device was measured with one worker,
``efficiency`` = rate / (workers × one-worker rate). ``--pin-workers`` pins process workers to
cores (``scenes.pin_workers``). ``--torch-threads-update N`` overrides the config's
``torch_threads_update`` (torch threads of the discriminator fit and PPO epochs; a different
count changes the discriminator's float rounding, so results differ from the config's) and the
rows carry ``torch_threads_update``. Run it on an otherwise idle machine: the scene workers,
the trainer and torch's update threads all need the cores (two update threads on a busy
2-core machine wait on each other: see the README's Benchmarks section).

    python benchmarks/train_throughput.py [--json] [--updates N] [--config YAML ...]
        [--workers 1,2] [--scenes-per-env 1,5] [--backend process,hosted,ray] [--ray-nodes 1,2] [--repeats R] [--pin-workers]
        [--scenes ENTRY ...] [--torch-threads-update N]

``--scenes`` trains on other pool entries than the config's, e.g. a city scenario alone
(``--config configs/experiments/city/ingolstadt21.yaml --scenes data/sumo/ingolstadt21``);
the expert data are recorded from the config's recorded scenes.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

if __name__ == "__main__":
    # The learner's imports (torch, SB3). The scene workers are spawned processes that import
    # this script again as ``__mp_main__``; they need none of it (magail_sumo.env.slot_worker),
    # and importing it would add about 0.5 GiB to each and measure workers unlike training's.
    import torch

    from magail_sumo.config import load_config
    from magail_sumo.env.scene_pool import is_city, resolve_pool
    from magail_sumo.env.scene_specs import scene_specs
    from magail_sumo.expert import ExpertDataset, record_expert
    from magail_sumo.sensors.observation import observation_names
    from magail_sumo.training.bc import behavioural_cloning
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.discriminator_loss import (DiscriminatorLossConfig,
                                                         discriminator_loss)
    from magail_sumo.training.trainer import GailRun, make_discriminator


def loop_throughput(cfg: TrainConfig, expert: ExpertDataset, updates: int) -> dict:
    run = GailRun(cfg, expert)
    try:
        run.policy.obs_normalizer.update(torch.as_tensor(expert.s))
        if cfg.bc.epochs > 0:  # as training does (untimed): agents live longer than untrained
            behavioural_cloning(run.policy, expert, cfg.bc.epochs, cfg.bc.batch_size,
                                cfg.bc.learning_rate, cfg.seed)
        run.run_update()  # warm-up: worker start, numba, first reset
        s0, t0 = run.venv.agent_steps, time.perf_counter()
        for _ in range(updates):
            run.run_update()
        dt = time.perf_counter() - t0
        return {"agent_steps": run.venv.agent_steps - s0, "seconds": dt,
                "agent_steps_per_s": (run.venv.agent_steps - s0) / dt,
                "workers": len(run.venv.specs)}
    finally:
        run.close()


def disc_throughput(cfg: TrainConfig, expert: ExpertDataset, device: str, repeats: int = 20
                    ) -> float:
    d = cfg.discriminator
    disc = make_discriminator(replace(cfg, device=device), 2 * expert.obs_dim)
    disc.normalizer.update(torch.as_tensor(expert.tokens, device=device))
    opt = torch.optim.AdamW(disc.parameters(), lr=d.learning_rate)
    rng = np.random.default_rng(0)
    loss_cfg = DiscriminatorLossConfig(d.gp_coef, d.logit_reg)
    batches = [(expert.sample_scene_steps(d.batch_size, rng),
                expert.sample_scene_steps(d.batch_size, rng)) for _ in range(repeats + 3)]
    tokens, elapsed = 0, 0.0
    for k, (e, p) in enumerate(batches):
        t = lambda a: torch.as_tensor(a, device=device)  # noqa: E731
        if device == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        pos = {} if e.pos is None else {"expert_pos": t(e.pos), "policy_pos": t(p.pos)}
        out = discriminator_loss(disc, t(e.x), t(e.mask), t(p.x), t(p.mask), loss_cfg, **pos)
        opt.zero_grad()
        out.total.backward()
        opt.step()
        if device == "cuda":
            torch.cuda.synchronize()
        if k >= 3:
            elapsed += time.perf_counter() - t0
            tokens += int(e.mask.sum() + p.mask.sum())
    return tokens / elapsed


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="one JSON object per row")
    ap.add_argument("--updates", type=int, default=3, help="timed PPO updates per measurement")
    ap.add_argument("--config", type=Path, action="append",
                    help="training config (repeatable; default "
                         "configs/experiments/womd3/magail.yaml)")
    ap.add_argument("--workers", default=None,
                    help="comma-separated scene-worker counts (default: the config's)")
    ap.add_argument("--backend", default="process", help="comma-separated: process, hosted, ray")
    ap.add_argument("--scenes-per-env", default=None,
                    help="comma-separated workers.scenes_per_env values (recorded scenes a "
                         "worker steps as one tiled env; default: the config's)")
    ap.add_argument("--ray-nodes", default="1",
                    help="comma-separated node counts of the local Ray cluster")
    ap.add_argument("--repeats", type=int, default=1, help="runs per row (median reported)")
    ap.add_argument("--scenes", nargs="+", default=None,
                    help="train on these pool entries instead of the config's (e.g. a city "
                         "scenario alone); the expert data still come from the config's "
                         "recorded scenes")
    ap.add_argument("--pin-workers", action="store_true", help="pin scene workers to cores")
    ap.add_argument("--torch-threads-update", type=int, default=None,
                    help="torch threads of the discriminator fit and PPO epochs (default: the "
                         "config's torch_threads_update; another count changes results)")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    configs = args.config or [ROOT / "configs" / "experiments" / "womd3" / "magail.yaml"]
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    workers = [None] if args.workers is None else [int(w) for w in args.workers.split(",")]
    per_env = [None] if args.scenes_per_env is None else \
        [int(k) for k in args.scenes_per_env.split(",")]
    setups = []
    for backend in args.backend.split(","):
        nodes = [int(n) for n in args.ray_nodes.split(",")] if backend == "ray" else [1]
        setups += [(backend, n) for n in nodes]
    with tempfile.TemporaryDirectory() as tmp:
        for path in configs:
            base = load_config(path, TrainConfig)
            one: dict = {}
            for backend, nodes in setups:
                cluster = _start_cluster(nodes) if backend == "ray" else None
                try:
                    for w, k in [(w, k) for w in workers for k in per_env]:
                        for row in _measure(path, base, devices, args, Path(tmp), backend,
                                            nodes, w, cluster, k):
                            key = (row["config"], row["backend"], row["nodes"], row["device"],
                                   row["scenes_per_env"])
                            if row["workers"] == 1:
                                one[key] = row["agent_steps_per_s"]
                            if key in one:
                                row["efficiency"] = round(
                                    row["agent_steps_per_s"] / (row["workers"] * one[key]), 3)
                            _print(row, args)
                finally:
                    if cluster is not None:
                        import ray

                        ray.shutdown()
                        cluster.shutdown()
    return 0


def _start_cluster(nodes: int):
    """A local Ray cluster of ``nodes`` nodes sharing this machine's cores."""
    import os

    import ray
    from ray.cluster_utils import Cluster

    cores = len(os.sched_getaffinity(0))
    per = max(1, cores // nodes)
    c = Cluster(initialize_head=True, head_node_args={"num_cpus": per})
    for _ in range(nodes - 1):
        c.add_node(num_cpus=per)
    c.wait_for_nodes()
    ray.init(address=c.address, include_dashboard=False, log_to_driver=False,
             logging_level="ERROR")
    return c


def _print(row: dict, args) -> None:
    if args.json:
        print(json.dumps(row), flush=True)
        return
    eff = f", efficiency {row['efficiency']:.2f}" if "efficiency" in row else ""
    print(f"{row['config']} {row['device']} {row['backend']} x{row['workers']} workers "
          f"({row['nodes']} node(s), {row['scenes_per_env']} scene(s) per env): whole loop {row['agent_steps_per_s']:.0f} agent-steps/s "
          f"(runs {row['agent_steps_per_s_runs']}){eff}; discriminator fwd+bwd "
          f"{row['disc_tokens_per_s']:.0f} tokens/s", flush=True)


def _measure(path: Path, base: TrainConfig, devices: list[str], args, tmp: Path,
             backend: str, nodes: int, workers: int | None, cluster,
             per_env: int | None = None) -> list[dict]:
    """The rows of one config and worker setup (expert data recorded once per layout)."""
    nets = tmp / "networks"
    files = [str(ROOT / f) if not Path(f).is_absolute() else f for f in base.scenes.files]
    recorded = [f for f in resolve_pool(files) if not is_city(f)]
    expert_dir = tmp / f"expert-{base.env.observation.layout}-{abs(hash(tuple(recorded)))}"
    if not expert_dir.exists():
        specs = scene_specs(sorted({r.path for r in recorded}), nets)
        record_expert(specs, expert_dir, base.env.observation, base.env.limits, workers=2)
    if args.scenes:
        files = [str(Path(f).resolve()) for f in args.scenes]
    expert = ExpertDataset(expert_dir, observation_names(base.env.observation))
    rows = []
    for device in devices:
        w = base.workers
        cfg = replace(base, device=device, expert_dir=str(expert_dir),
                      scenes=replace(base.scenes, files=tuple(files), networks=str(nets),
                                     pin_workers=args.pin_workers or base.scenes.pin_workers),
                      workers=replace(w, backend=backend, count=workers or w.count,
                                      scenes_per_env=per_env or w.scenes_per_env,
                                      ray=replace(w.ray, address=None if cluster is None
                                                  else cluster.address)))
        if args.torch_threads_update is not None:
            cfg = replace(cfg, torch_threads_update=args.torch_threads_update)
        torch.set_num_threads(max(1, cfg.torch_threads))
        runs = []
        for _ in range(max(1, args.repeats)):
            loop = loop_throughput(cfg, expert, args.updates)
            runs.append(round(loop["agent_steps_per_s"], 1))
        tok = disc_throughput(cfg, expert, device)
        name = path.name if not args.scenes else \
            f"{path.name}[{','.join(Path(f).name for f in args.scenes)}]"
        rows.append({"device": device, "config": name, "backend": backend,
                     "workers": loop["workers"], "nodes": nodes,
                     "scenes_per_env": cfg.workers.scenes_per_env,
                     "torch_threads_update": cfg.torch_threads_update or cfg.torch_threads,
                     "agent_steps_per_s": float(np.median(runs)),
                     "agent_steps_per_s_runs": runs, "disc_tokens_per_s": round(tok, 1)})
    return rows


if __name__ == "__main__":
    sys.exit(main())
