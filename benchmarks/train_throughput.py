"""Training throughput: the whole MAGAIL loop and the discriminator alone.

* ``agent_steps_per_s``: agent-steps (active slot-steps) per second of complete PPO updates —
  rollout in the scene workers with imitation rewards, discriminator training, PPO epochs —
  with a config (default ``configs/magail.yaml``) on its real scenes; the first update is
  excluded as warm-up, and a config's behavioural-cloning initialisation runs first, untimed,
  as in training (a BC policy keeps more agents alive per step than an untrained one);
* ``disc_tokens_per_s``: vehicle tokens per second through the discriminator loss forward +
  backward (GAIL BCE + gradient penalty), expert and policy tokens counted, at the config's
  transformer size and batch.

CPU always, GPU too when ``torch.cuda.is_available()``. ``--config`` may be repeated (one row
per config and device, with a ``config`` key); ``--pin-workers`` pins the scene workers to cores
(``scenes.pin_workers``). Run it on an otherwise idle machine: the scene workers, the trainer
and torch's update threads all need the cores.

    python benchmarks/train_throughput.py [--json] [--updates N] [--config YAML ...] [--pin-workers]
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
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from magail_sumo.config import load_config  # noqa: E402
from magail_sumo.env.vec_env import scene_specs  # noqa: E402
from magail_sumo.expert import ExpertDataset, record_expert  # noqa: E402
from magail_sumo.sensors.observation import observation_names  # noqa: E402
from magail_sumo.training.bc import behavioural_cloning  # noqa: E402
from magail_sumo.training.config import TrainConfig  # noqa: E402
from magail_sumo.training.discriminator_loss import (  # noqa: E402
    DiscriminatorLossConfig, discriminator_loss)
from magail_sumo.training.trainer import GailRun, make_discriminator  # noqa: E402


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
                "agent_steps_per_s": (run.venv.agent_steps - s0) / dt}
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
    ap.add_argument("--json", action="store_true", help="one JSON object per device")
    ap.add_argument("--updates", type=int, default=3, help="timed PPO updates per device")
    ap.add_argument("--config", type=Path, action="append",
                    help="training config (repeatable; default configs/magail.yaml)")
    ap.add_argument("--pin-workers", action="store_true", help="pin scene workers to cores")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    configs = args.config or [ROOT / "configs" / "magail.yaml"]
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    with tempfile.TemporaryDirectory() as tmp:
        for path in configs:
            _measure(path, load_config(path, TrainConfig), devices, args, Path(tmp),
                     len(configs) > 1)
    return 0


def _measure(path: Path, base: TrainConfig, devices: list[str], args, tmp: Path,
             name_rows: bool) -> None:
    """Print the rows of one config (expert data recorded once per observation layout)."""
    nets = tmp / "networks"
    files = [str(ROOT / f) if not Path(f).is_absolute() else f for f in base.scenes.files]
    specs = scene_specs(files, nets)
    expert_dir = tmp / f"expert-{base.env.observation.layout}-{abs(hash(tuple(files)))}"
    if not expert_dir.exists():
        record_expert(specs, expert_dir, base.env.observation, base.env.limits, workers=2)
    expert = ExpertDataset(expert_dir, observation_names(base.env.observation))
    for device in devices:
        cfg = replace(base, device=device, expert_dir=str(expert_dir),
                      scenes=replace(base.scenes, files=tuple(files), networks=str(nets),
                                     pin_workers=args.pin_workers or base.scenes.pin_workers))
        torch.set_num_threads(max(1, cfg.torch_threads))
        loop = loop_throughput(cfg, expert, args.updates)
        tok = disc_throughput(cfg, expert, device)
        row = {"device": device, "agent_steps_per_s": round(loop["agent_steps_per_s"], 1),
               "disc_tokens_per_s": round(tok, 1)}
        if name_rows:
            row["config"] = path.name
        if args.json:
            print(json.dumps(row), flush=True)
        else:
            print(f"{path.name} {device}: whole loop {row['agent_steps_per_s']:.0f} "
                  f"agent-steps/s ({loop['agent_steps']} agent-steps in {loop['seconds']:.1f} s, "
                  f"{args.updates} updates); discriminator fwd+bwd "
                  f"{row['disc_tokens_per_s']:.0f} tokens/s", flush=True)


if __name__ == "__main__":
    sys.exit(main())
