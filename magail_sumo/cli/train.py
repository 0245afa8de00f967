"""``magail-sumo train``: MAGAIL / GAIL / behavioural-cloning training from a YAML config."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train a driving policy (MAGAIL, GAIL, BC)",
                       description="Train from a strict YAML config (configs/magail.yaml, "
                                   "configs/gail_mlp.yaml, configs/bc.yaml); the run directory "
                                   "gets config.yaml, environment.json, checkpoints/ and tb/.")
    p.add_argument("--config", required=True, type=Path, metavar="YAML", help="training config")
    p.add_argument("--resume", type=Path, default=None, metavar="RUN_DIR",
                   help="continue a run from RUN_DIR/checkpoints/latest.pt")
    p.add_argument("--run-dir", type=Path, default=None, metavar="DIR",
                   help="run directory (default: OUT_DIR/<algorithm>-seed<seed>-<time>)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import warnings

    from magail_sumo.config import load_config
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.trainer import train

    warnings.filterwarnings("ignore", message=".*mini-batch size.*")
    cfg = load_config(args.config, TrainConfig)
    run_dir = train(cfg, run_dir=args.run_dir, resume=args.resume)
    print(f"run: {run_dir}")
    return 0
