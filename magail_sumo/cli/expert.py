"""``magail-sumo expert``: record expert demonstrations (log replay through the sensors)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from magail_sumo.cli.argtypes import timeout_s
from magail_sumo.config import load_config
from magail_sumo.outputs import OutputError, claim_output_dir, printable


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("expert", help="record expert demonstrations as Parquet",
                       description="Replay every scene's log through the env sensors with "
                                   "inverse-dynamics actions and write DIR/<id>.parquet "
                                   "(s, s', action, done, ids, poses) and DIR/metadata.json. "
                                   "DIR must be new, empty or written by magail-sumo.")
    p.add_argument("scenes", nargs="+", metavar="SCENES", help="WOMD TFRecord / ScenarioNet files")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    p.add_argument("--networks", type=Path, default=Path("networks"), metavar="DIR",
                   help="converted bundles (DIR/<id>/); scenes without one are converted there")
    p.add_argument("--config", type=Path, default=None, metavar="YAML",
                   help="training config whose env.observation and env.limits to use")
    p.add_argument("--workers", type=int, default=1, metavar="N", help="parallel processes")
    p.add_argument("--timeout-s", type=timeout_s, default=1800.0, metavar="S",
                   help="seconds one scene may take (conversion, recording) before it is "
                        "killed and reported failed (default 1800; 'none': no limit)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
    from magail_sumo.env.scene_specs import scene_specs
    from magail_sumo.expert import record_expert

    observation = limits = None
    if args.config is not None:
        # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
        from magail_sumo.training.config import TrainConfig

        cfg = load_config(args.config, TrainConfig)
        observation, limits = cfg.env.observation, cfg.env.limits

    # refuse a folder that is not ours before converting anything
    claim_output_dir(args.out, "expert", ["metadata.json"])
    errors: list[str] = []
    specs = scene_specs(args.scenes, args.networks, errors=errors, time_budget_s=args.timeout_s)
    for e in errors:
        print(f"error: {e}", file=sys.stderr, flush=True)
    bar = tqdm(total=len(specs), desc="scenes", unit="scene", file=sys.stderr, leave=False,
               disable=not sys.stderr.isatty())

    def done(sc: dict) -> None:
        bar.write(f"{printable(sc['scenario_id'])}: {sc['rows']} transitions, {sc['vehicles']} vehicles, "
                  f"{sc['steps']} steps -> {args.out / sc['parquet']}", file=sys.stdout)
        bar.update(1)

    def failed(spec, reason: str) -> None:
        errors.append(reason)
        bar.write(f"error: {reason}", file=sys.stderr)
        bar.update(1)

    try:
        meta = record_expert(specs, args.out, observation, limits, workers=args.workers,
                             on_scene=done, on_error=failed, timeout_s=args.timeout_s)
    except OSError as exc:  # a full disk, a read-only folder: one line, no traceback

        raise OutputError(f"{exc.filename or args.out}: cannot write "
                          f"({exc.strerror or type(exc).__name__})") from None
    finally:
        bar.close()
    if errors:
        print(f"recorded {len(meta['scenes'])} scene(s); {len(errors)} problem(s) reported "
              "above", file=sys.stderr)
    return 1 if errors else 0
