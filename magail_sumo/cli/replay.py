"""``magail-sumo replay``: drive a recorded scene through the env and write a top-down video."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from magail_sumo.cli.progress import progress

POLICIES = ("log", "random")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="render a scene run through the env as a video",
                       description="Run one recorded scene through the SUMO env (log replay: every "
                                   "vehicle follows its recording by inverse dynamics; random: "
                                   "uniform random actions) and write a top-down GIF or MP4.")
    p.add_argument("scene", type=Path, metavar="SCENE", help="scene file (WOMD / ScenarioNet)")
    p.add_argument("--out", required=True, type=Path, metavar="FILE", help="FILE.gif or FILE.mp4")
    p.add_argument("--bundle", type=Path, help="converted scenario folder "
                   "(default: networks/<id> when present, else converted on the fly)")
    p.add_argument("--policy", choices=POLICIES, default="log")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fps", type=int, default=10)
    p.add_argument("--size", type=int, default=512, help="frame height and width in pixels")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from converters import load_scene
    from converters.sumo.scenario import ConvertOptions, convert_scene
    from magail_sumo.env import REPLAY_LIMITS, EnvConfig, SumoDrivingEnv, expert_actions
    from magail_sumo.env.video import FORMATS, write_video
    from magail_sumo.errors import MagailSumoError

    if args.out.suffix.lower() not in FORMATS:
        raise MagailSumoError(f"{args.out}: unsupported video format (use {' or '.join(FORMATS)})")
    scene = load_scene(args.scene)
    with tempfile.TemporaryDirectory() as tmp:
        bundle = args.bundle
        if bundle is None and Path("networks", scene.scenario_id).is_dir():
            bundle = Path("networks", scene.scenario_id)
        if bundle is None:
            rep = convert_scene(scene, Path(tmp), ConvertOptions(baseline=False))
            if rep.status != "ok":
                raise MagailSumoError(f"{args.scene}: conversion failed: {rep.reason}")
            bundle = Path(tmp) / scene.scenario_id
        log = args.policy == "log"
        cfg = EnvConfig(terminate_on=() if log else ("collision", "off_road"),
                        limits=REPLAY_LIMITS if log else EnvConfig().limits,
                        render_size=(args.size, args.size))
        env = SumoDrivingEnv(scene, bundle, cfg, render_mode="rgb_array")
        rng = np.random.default_rng(args.seed)
        env.reset(seed=args.seed)
        frames = [env.render()]
        for _ in progress(range(scene.num_steps - 1), desc="steps", unit="step"):
            if not env.agents:
                break
            acts = expert_actions(env) if log else {
                a: rng.uniform(-1, 1, 2).astype(np.float32) for a in env.agents}
            env.step(acts)
            frames.append(env.render())
        env.close()
    n = write_video(args.out, frames, args.fps)
    print(f"{scene.scenario_id}: {n} frames ({args.policy}) -> {args.out}", file=sys.stderr)
    return 0
