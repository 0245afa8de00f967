"""``magail-sumo train``: MAGAIL / GAIL / behavioural-cloning training from a YAML config.

The config file may extend others (``extends:``, :mod:`magail_sumo.config`); ``--set KEY=VALUE``
(repeatable) changes one setting for this run, checked as the file's settings are (an unknown
key or a value out of range is refused naming the key), so that another seed, scene set or
update budget needs no copy of the file. The run directory records the config with every
setting resolved.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from magail_sumo.config import load_config, to_dict
from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import MARKER, inside, os_error, read_marker, remove_owned, write_text
from magail_sumo.cli.progress import PhaseBars


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train a driving policy (MAGAIL, GAIL, BC)",
                       description="Train from a strict YAML config (configs/demo.yaml, "
                                   "configs/experiments/*/*.yaml; configs/README.md), changed "
                                   "for this run by --set KEY=VALUE; the run directory gets "
                                   "config.yaml (every setting resolved), environment.json, "
                                   "checkpoints/ and tb/.")
    p.add_argument("--config", type=Path, metavar="YAML",
                   help="training config (required unless --upgrade-checkpoint)")
    p.add_argument("--resume", type=Path, default=None, metavar="RUN_DIR",
                   help="continue a run from RUN_DIR/checkpoints/latest.pt")
    p.add_argument("--run-dir", type=Path, default=None, metavar="DIR",
                   help="run directory (default: OUT_DIR/<algorithm>-seed<seed>-<time>)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", dest="overrides",
                   help="change one setting of the config for this run (repeatable, applied in "
                        "order after the file): KEY a dotted setting name (updates, "
                        "ppo.learning_rate, env.observation.leader, scenes.split), VALUE read "
                        "as YAML (5, 0.0003, true, null, '[a.tfrecord, b.pkl]'); checked as "
                        "the file's settings are, recorded in the run's config.yaml")
    p.add_argument("--seed", type=int, default=None,
                   help="override the config's seed (the same as --set seed=N)")
    p.add_argument("--print-config", action="store_true",
                   help="print the config with every setting resolved (extends, --set and the "
                        "defaults) as YAML, and exit without training")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier run in --run-dir: removes only what train wrote "
                        "there (a folder train did not write is refused)")
    p.add_argument("--upgrade-checkpoint", type=Path, default=None, metavar="FILE",
                   help="convert a checkpoint written by magail_sumo < checkpoint format 2 "
                        "(pickled numpy objects) in place and exit; loading it can run code "
                        "the file holds, so it needs --trust: only for a file you trust")
    p.add_argument("--trust", action="store_true",
                   help="with --upgrade-checkpoint: the file is trusted")
    p.set_defaults(func=run)


def _clear_run_dir(d: Path) -> None:
    """Remove the earlier run in ``d``: only what ``train`` recorded as its own in the folder's
    marker; :class:`~magail_sumo.outputs.OutputError` (nothing removed) for a folder train did
    not write. Other files stay, and the folder stays marked as a run directory."""
    if not d.is_dir() or not any(d.iterdir()):
        return
    remove_owned(d, "train")
    if d.is_dir() and read_marker(d) is None:  # files of the user's left: keep it ours
        write_text(inside(d, MARKER), json.dumps({"tools": {"train": []}}, indent=1))


def run(args: argparse.Namespace) -> int:
    import warnings

    # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.preflight import check_train_config
    from magail_sumo.training.trainer import train


    if args.upgrade_checkpoint is not None:
        # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
        from magail_sumo.training.trainer import upgrade_checkpoint

        print(f"upgraded: {upgrade_checkpoint(args.upgrade_checkpoint, trust=args.trust)}")
        return 0
    if args.config is None:
        raise MagailSumoError("train: --config is required")
    warnings.filterwarnings("ignore", message=".*mini-batch size.*")
    overrides = list(args.overrides) + ([f"seed={args.seed}"] if args.seed is not None else [])
    cfg = load_config(args.config, TrainConfig, overrides=overrides)
    if args.print_config:
        import yaml


        print(yaml.safe_dump(to_dict(cfg), sort_keys=False), end="")
        return 0
    check_train_config(cfg, args.config)  # device, scene files, start_step: before any set-up
    bars = PhaseBars()
    try:
        if args.overwrite and args.run_dir is not None and args.resume is None:
            _clear_run_dir(args.run_dir)
        run_dir = train(cfg, run_dir=args.run_dir, resume=args.resume, log=bars.log,
                        progress=bars)
    except OSError as exc:  # a full disk, a read-only folder: one line naming the file
        raise os_error(exc, args.run_dir or args.resume or cfg.out_dir) from exc
    finally:
        bars.close()
    print(f"run: {run_dir}")
    return 0
