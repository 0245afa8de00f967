"""``magail-sumo evaluate``: WOSAC-protocol rollouts of a policy and the baselines, as Parquet."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from magail_sumo.cli.argtypes import timeout_s


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="closed-loop rollouts of a policy and the baselines",
                       description="Simulate every object valid at each scene's current step "
                                   "for 80 steps (WOSAC protocol) with the policy under test "
                                   "and the baselines; write DIR/rollouts/<method>/<scenario>"
                                   ".parquet and DIR/manifest.json (DIR: new, empty or written "
                                   "by magail-sumo).")
    p.add_argument("--policy", required=True, metavar="POLICY",
                   help="logreplay | constvel | sumo | random | pretrained[:NAME] (a shipped "
                        "policy; $MAGAIL_SUMO_PRETRAINED_DIR: another registry folder) | "
                        "CHECKPOINT | module:factory")
    p.add_argument("--name", metavar="NAME",
                   help="method name of the policy in the rollouts, manifest and report "
                        "(default: the built-in's name; pretrained:NAME: NAME; a checkpoint "
                        "RUN/checkpoints/latest.pt: RUN's folder name; a factory's name)")
    p.add_argument("--scenes", nargs="+", required=True, metavar="FILE",
                   help="scene files (WOMD TFRecords, ScenarioNet pickles or folders)")
    p.add_argument("--rollouts", type=int, default=32, metavar="R", help="rollouts per scene")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    p.add_argument("--baselines", default="logreplay,constvel,sumo", metavar="LIST",
                   help="comma-separated baselines run alongside (default: all three; "
                        "'none' for none)")
    p.add_argument("--networks", type=Path, metavar="DIR",
                   help="folder of converted bundles DIR/<scenario_id>/ to reuse (else scenes "
                        "are converted into OUT/networks)")
    p.add_argument("--export-submission", type=Path, metavar="FILE.binproto",
                   help="also write the policy's rollouts as a SimAgentsChallengeSubmission")
    p.add_argument("--fcd-rollouts", type=int, default=0, metavar="K",
                   help="also write the first K rollouts of every scene and method as SUMO FCD "
                        "with a replay config: sumo-gui -c DIR/fcd/<method>/<scenario>/"
                        "rollout000.sumocfg (default 0: none)")
    p.add_argument("--seed", type=int, default=0, help="run seed (rollout r uses a seed "
                                                       "derived from it and r)")
    p.add_argument("--deterministic", action="store_true",
                   help="a checkpoint policy acts with the tanh of its Gaussian mean, the same "
                        "in every rollout (default: it samples its actions, seeded per rollout)")
    p.add_argument("--workers", type=int, default=2, metavar="N",
                   help="worker processes for SUMO rollouts")
    p.add_argument("--timeout-s", type=timeout_s, default=1800.0, metavar="S",
                   help="seconds one worker job (a batch of up to 8 rollouts of one method on "
                        "one scene, or a scene's conversion) may take before it is killed and "
                        "reported failed (default 1800; 'none': no limit)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from magail_sumo.evaluation.rollouts import evaluate
    from magail_sumo.outputs import OutputError

    base = [] if args.baselines.strip().lower() == "none" else \
        [b.strip() for b in args.baselines.split(",") if b.strip()]
    clock = time.perf_counter()
    try:
        res = evaluate(args.scenes, args.policy, args.out, n_rollouts=args.rollouts,
                       baselines=base, seed=args.seed, workers=args.workers,
                       networks=args.networks, submission=args.export_submission,
                       timeout_s=args.timeout_s, fcd_rollouts=args.fcd_rollouts,
                       name=args.name, deterministic=args.deterministic)
    except OSError as exc:  # a full disk, a read-only folder: one line, no traceback
        raise OutputError(f"{exc.filename or args.out}: cannot write "
                          f"({exc.strerror or type(exc).__name__})") from None
    print(f"evaluated {len(res.done)} scene/method pair(s) in {time.perf_counter() - clock:.1f} s"
          f" -> {args.out}" + (f"; {len(res.errors)} problem(s) reported above"
                               if res.errors else ""), file=sys.stderr)
    return 1 if res.errors or not res.done else 0
