"""Training throughput: the whole MAGAIL loop and the discriminator alone.

* ``agent_steps_per_s``: agent-steps (active slot-steps) per second of complete PPO updates —
  rollout in the scene workers with imitation rewards, discriminator training, PPO epochs —
  with ``configs/magail.yaml`` on the real scenes (first update excluded as warm-up);
* ``disc_tokens_per_s``: vehicle tokens per second through the discriminator loss forward +
  backward (GAIL BCE + gradient penalty), expert and policy tokens counted, at the config's
  transformer size and batch.

CPU always, GPU too when ``torch.cuda.is_available()``.

    python benchmarks/train_throughput.py [--json] [--updates N] [--config YAML]
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
from magail_sumo.training.config import TrainConfig  # noqa: E402
from magail_sumo.training.discriminator_loss import (  # noqa: E402
    DiscriminatorLossConfig, discriminator_loss)
from magail_sumo.training.trainer import GailRun, make_discriminator  # noqa: E402


def loop_throughput(cfg: TrainConfig, expert: ExpertDataset, updates: int) -> dict:
    run = GailRun(cfg, expert)
    try:
        run.policy.obs_normalizer.update(torch.as_tensor(expert.s))
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
        out = discriminator_loss(disc, t(e.x), t(e.mask), t(p.x), t(p.mask), loss_cfg)
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
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "magail.yaml")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    base = load_config(args.config, TrainConfig)
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    with tempfile.TemporaryDirectory() as tmp:
        nets = Path(tmp) / "networks"
        files = [str(ROOT / f) if not Path(f).is_absolute() else f for f in base.scenes.files]
        specs = scene_specs(files, nets)
        record_expert(specs, Path(tmp) / "expert", base.env.observation, base.env.limits,
                      workers=2)
        expert = ExpertDataset(Path(tmp) / "expert", observation_names(base.env.observation))
        for device in devices:
            cfg = replace(base, device=device, expert_dir=str(Path(tmp) / "expert"),
                          scenes=replace(base.scenes, files=tuple(files), networks=str(nets)))
            torch.set_num_threads(max(1, cfg.torch_threads))
            loop = loop_throughput(cfg, expert, args.updates)
            torch.set_num_threads(torch.get_num_threads())
            tok = disc_throughput(cfg, expert, device)
            row = {"device": device, "agent_steps_per_s": round(loop["agent_steps_per_s"], 1),
                   "disc_tokens_per_s": round(tok, 1)}
            if args.json:
                print(json.dumps(row))
            else:
                print(f"{device}: whole loop {row['agent_steps_per_s']:.0f} agent-steps/s "
                      f"({loop['agent_steps']} agent-steps in {loop['seconds']:.1f} s, "
                      f"{args.updates} updates); discriminator fwd+bwd "
                      f"{row['disc_tokens_per_s']:.0f} tokens/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
