"""``magail-sumo evaluate``: WOSAC-protocol rollouts of a policy and the baselines, as Parquet;
with ``--city``, the policy on whole SUMO cities against SUMO's default drivers."""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

from magail_sumo.cli.argtypes import bounded, timeout_s
from magail_sumo.outputs import OutputError, check_writable_file
from magail_sumo.cli.progress import PhaseBars


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("evaluate", help="closed-loop rollouts of a policy and the baselines",
                       description="Simulate every object valid at each scene's current step "
                                   "for 80 steps (WOSAC protocol) with the policy under test "
                                   "and the baselines; write DIR/rollouts/<method>/<scenario>"
                                   ".parquet and DIR/manifest.json (DIR: new, empty or written "
                                   "by magail-sumo). With --city, the policy also drives "
                                   "whole SUMO city scenarios against SUMO's default drivers "
                                   "(DIR/city.json, DIR/city/<scenario>/<method>/).")
    p.add_argument("--policy", required=True, metavar="POLICY",
                   help="logreplay | constvel | sumo | random | pretrained[:NAME] (a shipped "
                        "policy; $MAGAIL_SUMO_PRETRAINED_DIR: another registry folder) | "
                        "CHECKPOINT | module:factory | guarded:POLICY (that policy driven "
                        "through the gap guard)")
    p.add_argument("--name", metavar="NAME",
                   help="method name of the policy in the rollouts, manifest and report "
                        "(default: the built-in's name; pretrained:NAME: NAME; a checkpoint "
                        "RUN/checkpoints/latest.pt: RUN's folder name; a factory's name)")
    p.add_argument("--scenes", nargs="+", metavar="FILE",
                   help="scene files (WOMD TFRecords, ScenarioNet pickles or folders); "
                        "--scenes, --city or both")
    p.add_argument("--city", nargs="+", action="extend", metavar="SUMOCFG",
                   help="plain SUMO city scenarios (.sumocfg, e.g. data/sumo/ingolstadt21/"
                        "ingolstadt21.sumocfg; repeatable): the policy drives up to "
                        "--city-max-agents vehicles, the rest SUMO traffic, and SUMO's default "
                        "drivers run over the same window; SUMO's tripinfo / edgeData / "
                        "statistics outputs of both go into DIR/city.json")
    p.add_argument("--city-steps", type=bounded(int, 1), default=3000, metavar="N",
                   help="0.1-s steps of each city run (default 3000: 5 min)")
    p.add_argument("--city-warmup-s", type=bounded(float, 0.0), default=600.0, metavar="S",
                   help="seconds SUMO drives a city alone before the window (default 600)")
    p.add_argument("--city-max-agents", type=bounded(int, 1), default=64, metavar="K",
                   help="policy-driven vehicles alive at once in a city (default 64)")
    p.add_argument("--city-control-fraction", type=bounded(float, 0.0, 1.0), default=1.0,
                   metavar="F", help="share of a city's vehicles that may become agents "
                                     "(seeded; default 1)")
    p.add_argument("--city-agent-classes", default="passenger", metavar="C,C",
                   help="SUMO vehicle classes that may become agents (default passenger: "
                        "buses, trams, trucks, bicycles and every vehicle with stops stay "
                        "SUMO-driven)")
    p.add_argument("--city-agent-tight-turns", action="store_true",
                   help="vehicles whose route turns tighter than a car can (SUMO's on-the-spot "
                        "turnarounds) become agents too (default: SUMO drives them)")
    p.add_argument("--city-demand-scale", type=float, default=1.0, metavar="F",
                   help="a city's demand times F in both runs (SUMO's --scale: vehicles "
                        "duplicated or left out, seeded; default 1)")
    p.add_argument("--city-unblock-s", type=float, default=10.0, metavar="S",
                   help="SUMO-driven vehicles that have waited S seconds next to an agent "
                        "standing as long on a junction stop giving way to standing agents "
                        "(0: never; default 10)")
    p.add_argument("--city-humans", metavar="EXPERT_DIR",
                   help="expert data of recorded human drivers (magail-sumo expert's --out): "
                        "city rows then give the JS divergence of the agents' and SUMO's "
                        "drivers' speed and acceleration distributions from the humans' "
                        "(DIR/city/<city>/kinematics.json holds the counts)")
    p.add_argument("--rollouts", type=int, default=32, metavar="R", help="rollouts per scene")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    p.add_argument("--baselines", default="logreplay,constvel,sumo", metavar="LIST",
                   help="comma-separated baselines run alongside (default: all three; "
                        "'none' for none)")
    p.add_argument("--networks", type=Path, metavar="DIR",
                   help="folder of converted bundles DIR/<scenario_id>/ to reuse (else scenes "
                        "are converted into OUT/networks)")
    p.add_argument("--export-submission", type=Path, metavar="FILE.binproto",
                   help="also write the policy's rollouts as a SimAgentsChallengeSubmission "
                        "(a file name, not a folder; checked before the rollouts)")
    p.add_argument("--fcd-rollouts", type=int, default=0, metavar="K",
                   help="also write the first K rollouts of every scene and method as SUMO FCD "
                        "with a replay config: sumo-gui -c DIR/fcd/<method>/<scenario>/"
                        "rollout000.sumocfg (default 0: none); K > 0 also records each city "
                        "run: DIR/city/<city>/<method>/fcd/<city>.sumocfg")
    p.add_argument("--seed", type=int, default=0, help="run seed (rollout r uses a seed "
                                                       "derived from it and r)")
    p.add_argument("--deterministic", action="store_true",
                   help="a checkpoint policy acts with the tanh of its Gaussian mean, the same "
                        "in every rollout (default: it samples its actions, seeded per rollout)")
    p.add_argument("--noise-scale", type=float, default=None, metavar="K",
                   help="a sampling policy draws tanh(mu + K*sigma*eps): K < 1 samples closer "
                        "to its mean (default: the policy's own, 1 or the sampling.noise_scale "
                        "of a pretrained policy's card)")
    p.add_argument("--workers", type=int, default=2, metavar="N",
                   help="worker processes for the policy's and SUMO's rollouts")
    p.add_argument("--timeout-s", type=timeout_s, default=1800.0, metavar="S",
                   help="seconds one worker batch (the rollouts of one method on one scene, "
                        "up to 32 of SUMO's; a process running several of a policy's batches "
                        "in turn gets as many times this), a scene's conversion, or one city "
                        "run may take before it is killed and reported failed (default 1800; "
                        "'none': no limit)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
    from magail_sumo.evaluation.city import CitySettings, check_policy, check_sumocfg
    from magail_sumo.evaluation.protocol import EvaluationError

    if not args.scenes and not args.city:
        raise EvaluationError("nothing to evaluate: give --scenes FILE..., --city SUMOCFG... "
                              "or both")
    if args.export_submission is not None:  # before the rollouts: a folder, an unwritable place
        check_writable_file(args.export_submission, "give a file name like sub.binproto")
    city = None
    if args.city:  # every city input checked before any scene runs
        city = CitySettings(steps=args.city_steps, warmup_s=args.city_warmup_s,
                            max_agents=args.city_max_agents,
                            control_fraction=args.city_control_fraction, seed=args.seed,
                            agent_classes=tuple(c.strip() for c in
                                                args.city_agent_classes.split(",") if c.strip()),
                            agent_tight_turns=args.city_agent_tight_turns,
                            unblock_s=args.city_unblock_s,
                            demand_scale=args.city_demand_scale,
                            fcd=args.fcd_rollouts > 0, humans=args.city_humans,
                            deterministic=args.deterministic, noise_scale=args.noise_scale,
                            timeout_s=args.timeout_s)
        for f in args.city:
            check_sumocfg(f)
        check_policy(args.policy, args.deterministic, args.noise_scale)
    clock = time.perf_counter()
    done, errors = 0, 0
    with _one_line_os_errors(args.out):
        if args.scenes:
            done, errors = _scenes(args)
        if city is not None:
            # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
            from magail_sumo.evaluation.city import evaluate_city

            res = evaluate_city(args.policy, args.city, args.out, city, name=args.name)
            done += len(res.rows)
            errors += len(res.errors)
    print(f"evaluated {done} scene/method pair(s) in {time.perf_counter() - clock:.1f} s"
          f" -> {args.out}" + (f"; {errors} problem(s) reported above" if errors else ""),
          file=sys.stderr)
    return 1 if errors or not done else 0


def _scenes(args: argparse.Namespace) -> tuple[int, int]:
    """Rollouts of the recorded scenes: (scene/method pairs done, problems)."""
    # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
    from magail_sumo.evaluation.protocol import WORKER_IMPORTS
    from magail_sumo.workers import start_job_server

    start_job_server(WORKER_IMPORTS)  # its imports beside this process's own (below)
    # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
    from magail_sumo.evaluation.runner import evaluate

    base = [] if args.baselines.strip().lower() == "none" else \
        [b.strip() for b in args.baselines.split(",") if b.strip()]
    bars = PhaseBars()
    try:
        res = evaluate(args.scenes, args.policy, args.out, n_rollouts=args.rollouts,
                       baselines=base, seed=args.seed, workers=args.workers,
                       networks=args.networks, submission=args.export_submission,
                       timeout_s=args.timeout_s, fcd_rollouts=args.fcd_rollouts,
                       name=args.name, deterministic=args.deterministic,
                       noise_scale=args.noise_scale, progress=bars)
    finally:
        bars.close()
    return len(res.done), len(res.errors)


@contextlib.contextmanager
def _one_line_os_errors(out: Path):
    """A full disk, a read-only folder: one line naming the file, no traceback."""
    try:
        yield
    except OSError as exc:
        raise OutputError(f"{exc.filename or out}: cannot write "
                          f"({exc.strerror or type(exc).__name__})") from None
