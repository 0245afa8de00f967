"""``magail-sumo replay``: drive a recorded scene through the env and write a top-down video;
or drive a SUMO city with a policy and record it as FCD to watch in ``sumo-gui``."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from converters import load_scene
from converters.sumo.bundle import BundleLayout, bundle_folder
from magail_sumo.cli.argtypes import bounded
from magail_sumo.cli.progress import progress
from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import (OutputError, atomic_path, check_writable_file, os_error,
                                 printable)

POLICIES = ("log", "random")
MAX_FPS = 100  #: GIF frame durations are whole 10 ms
MIN_SIZE, MAX_SIZE = 64, 4096  #: frame side (px); 4096² RGB frames are 48 MiB each


def check_writable(out: Path) -> None:
    """Refuse the video ``out`` before any slow work when it could not be written there
    (:func:`~magail_sumo.outputs.check_writable_file`: an existing folder, a parent that cannot
    be made, a folder that is not writable)."""
    check_writable_file(out, "give a FILE.gif or FILE.mp4")


def check_fcd(fcd: Path) -> Path:
    """The ``--fcd`` file name ``NAME.fcd.xml`` (``.fcd.xml`` added when missing), checked
    before any slow work: an existing folder is refused (``DIR: is a folder (give a file name
    like run.fcd.xml)``) rather than written beside, as is a place where the FCD or the two
    files beside it (``NAME.types.add.xml``, ``NAME.sumocfg``) could not be written."""
    # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
    from magail_sumo.sim.fcd import replay_paths

    hint = "give a file name like run.fcd.xml"
    if fcd.is_dir():
        raise OutputError(f"{printable(str(fcd))}: is a folder ({hint})")
    paths = replay_paths(fcd)
    for p in paths:
        check_writable_file(p, hint)
    return paths[0]


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="render a scene run through the env as a video",
                       description="Run one recorded scene through the SUMO env (log replay: every "
                                   "vehicle follows its recording by inverse dynamics; random: "
                                   "uniform random actions) and write a top-down GIF or MP4. "
                                   "Given a SUMO city (its configuration or folder), a policy "
                                   "(any --policy spec of evaluate) drives it and the run is "
                                   "recorded as FCD to open in sumo-gui (--fcd).")
    p.add_argument("scene", type=Path, metavar="SCENE",
                   help="scene file (WOMD / ScenarioNet), or a SUMO city's configuration or folder")
    p.add_argument("--out", type=Path, metavar="FILE",
                   help="FILE.gif or FILE.mp4 (recorded scenes; required for them)")
    p.add_argument("--bundle", type=Path, help="converted scenario folder "
                   "(default: networks/<id> when present, else converted on the fly)")
    p.add_argument("--policy", default="log", metavar="SPEC",
                   help="recorded scenes: log or random; a city: random, pretrained[:NAME], a "
                        "checkpoint or module:factory (default log)")
    p.add_argument("--steps", type=bounded(int, 1, 10**6), default=600,
                   help="a city: 0.1-s steps to drive (default 600: one minute)")
    p.add_argument("--city-warmup-s", type=bounded(float, 0.0, 86400.0), default=0.0,
                   metavar="S", help="a city: seconds SUMO drives alone first (default 0)")
    p.add_argument("--city-max-agents", type=bounded(int, 1, 10**5), default=64, metavar="K",
                   help="a city: policy-driven vehicles alive at once (default 64)")
    p.add_argument("--city-demand-scale", type=bounded(float, 0.01, 100.0), default=1.0,
                   metavar="F", help="a city: its demand times F (SUMO's --scale; default 1)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fps", type=bounded(int, 1, MAX_FPS), default=10,
                   help=f"frames per second of the video (1..{MAX_FPS})")
    p.add_argument("--size", type=bounded(int, MIN_SIZE, MAX_SIZE), default=512,
                   help=f"frame height and width in pixels ({MIN_SIZE}..{MAX_SIZE})")
    p.add_argument("--fcd", type=Path, metavar="FILE.fcd.xml",
                   help="also record the run as SUMO FCD (a file name, not a folder; "
                        "'.fcd.xml' added when missing), with FILE.types.add.xml and "
                        "FILE.sumocfg beside it replaying it on the converted network: "
                        "sumo-gui -c FILE.sumocfg")
    p.set_defaults(func=run)


class LiveRandomPolicy:
    """``--policy random``: uniform random actions in [-1, 1]² for the env's live agents, one
    draw per agent in the env's order (seeded)."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.env = None

    def begin(self, scene, env) -> None:
        self.env = env

    def act(self, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {a: self.rng.uniform(-1, 1, 2).astype(np.float32) for a in self.env.agents}


def _write_video_atomic(path: Path, frames: list, fps: int) -> int:
    """:func:`~magail_sumo.env.video.write_video` into a temporary file beside ``path`` (same
    suffix: it picks the format), renamed over ``path`` when complete: a crash or a full disk
    leaves the old video or none, never a half-written one."""
    import contextlib
    import os

    # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
    from magail_sumo.env.video import write_video

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem[:60]}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        n = write_video(tmp, frames, fps)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return n


def _write_fcd(env, path: Path, bundle: Path, temporary: bool):
    """Write the env's FCD recording and its replay config; a bundle converted into a
    temporary folder has its network and signal programs copied beside the FCD
    (``NAME.net.xml``, ``NAME.tll.xml``) so the config outlives it."""
    import shutil

    # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
    from magail_sumo.sim.fcd import replay_paths, write_replay

    if not temporary:
        return env.write_fcd(path)
    files = BundleLayout.of(bundle, env.scene.scenario_id)
    stem = replay_paths(path)[2].with_suffix("")
    copies = []
    for src in (files.net, files.signals):
        if src.is_file():
            dst = stem.with_name(stem.name + src.name[len(files.name):])
            with atomic_path(dst) as tmp:
                shutil.copyfile(src, tmp)
            copies.append(dst)
    return write_replay(env.fcd, path, copies[0], copies[1:])


def _umask() -> int:
    import os

    mask = os.umask(0)
    os.umask(mask)
    return mask


def run(args: argparse.Namespace) -> int:
    # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
    from converters.sumo.scenario import ensure_bundle
    from magail_sumo.agents import LogReplayPolicy, rollout
    from magail_sumo.env import REPLAY_LIMITS, EnvConfig, SumoDrivingEnv
    from magail_sumo.env.video import FORMATS

    city = _city(args.scene)
    if city is not None:
        return _replay_city(args, city)
    if args.policy not in POLICIES:
        raise MagailSumoError(f"--policy {args.policy}: a recorded scene replays with "
                              f"{' or '.join(POLICIES)} (a city takes any policy)")
    if args.out is None:
        raise MagailSumoError("--out FILE.gif or FILE.mp4 is required for a recorded scene")
    if args.out.suffix.lower() not in FORMATS:
        raise MagailSumoError(f"{args.out}: unsupported video format (use {' or '.join(FORMATS)})")
    check_writable(args.out)
    if args.fcd is not None:
        args.fcd = check_fcd(args.fcd)
    scene = load_scene(args.scene)
    with tempfile.TemporaryDirectory() as tmp:
        shipped = bundle_folder("networks", scene.scenario_id)  # a safe name: never a path
        bundle = args.bundle or ensure_bundle(scene, tmp, search=["networks"])
        log = args.policy == "log"
        cfg = EnvConfig(terminate_on=() if log else ("collision", "off_road"),
                        limits=REPLAY_LIMITS if log else EnvConfig().limits,
                        render_size=(args.size, args.size))
        env = SumoDrivingEnv(scene, bundle, cfg, render_mode="rgb_array")
        policy = LogReplayPolicy() if log else LiveRandomPolicy(args.seed)
        if args.fcd is not None:
            env.record_fcd()
        frames = []
        bar = progress(range(scene.num_steps - 1), desc="steps", unit="step")

        def frame(*_) -> None:
            next(bar, None)
            frames.append(env.render())

        try:
            rollout(env, policy, frame, seed=args.seed, max_steps=scene.num_steps - 1,
                    on_reset=lambda *_: frames.append(env.render()))
        finally:
            env.close()
        if args.fcd is not None:
            try:  # a full disk: one line naming the file
                fcd = _write_fcd(env, args.fcd, bundle, temporary=args.bundle is None
                                 and bundle != shipped)
            except OSError as exc:
                raise os_error(exc, args.fcd) from None
    if args.fcd is not None:
        print(f"{printable(scene.scenario_id)}: {fcd.records} FCD records -> {fcd.fcd}; "
              f"replay: sumo-gui -c {fcd.sumocfg}", file=sys.stderr)
    try:
        n = _write_video_atomic(args.out, frames, args.fps)
    except OSError as exc:  # a full disk, a read-only folder: one line, no traceback
        raise OutputError(f"{args.out}: cannot write ({exc.strerror or type(exc).__name__})") \
            from None
    print(f"{printable(scene.scenario_id)}: {n} frames ({args.policy}) -> {args.out}",
          file=sys.stderr)
    return 0


def _city(path: Path) -> Path | None:
    """The SUMO configuration ``path`` names (a configuration or its folder), or None."""
    # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
    from magail_sumo.sim.sumo_config import config_of

    return config_of(path)


def _replay_city(args: argparse.Namespace, cfg: Path) -> int:
    """A policy drives the city ``cfg`` for ``--steps`` steps; the run is written as FCD with
    its ``sumo-gui`` replay config (``--fcd``, required: a city has no top-down video)."""
    # lazy: a command's stack loads only when it runs (fast --help, no torch for inspect)
    from magail_sumo.agents import env_settings, rollout
    from magail_sumo.env import EnvConfig
    from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv
    from magail_sumo.evaluation.protocol import rollout_seed
    from magail_sumo.policies import make_policy

    if args.fcd is None:
        raise MagailSumoError(f"{cfg}: a city is watched in sumo-gui: give --fcd FILE.fcd.xml "
                              "(a city has no top-down video)")
    if args.out is not None:
        raise MagailSumoError(f"--out {args.out}: a city has no top-down video; its run is "
                              "the --fcd recording")
    fcd = check_fcd(args.fcd)
    policy = make_policy(args.policy, rollout_seed(args.seed, 0), False, None)
    city = CityEnvConfig.from_env(EnvConfig(**env_settings(policy)),
                                  max_agents=args.city_max_agents, control_fraction=1.0,
                                  warmup_s=args.city_warmup_s, max_steps=args.steps,
                                  demand_scale=args.city_demand_scale)
    env = SumoCityEnv(cfg, city)
    env.record_fcd()
    bar = progress(range(args.steps), desc="steps", unit="step")
    try:
        rollout(env, policy, lambda *_: next(bar, None), seed=args.seed, max_steps=args.steps,
                until_empty=False, live_only=True)
    finally:
        env.close()
    try:  # a full disk: one line naming the file
        files = env.write_fcd(fcd)
    except OSError as exc:
        raise os_error(exc, fcd) from None
    print(f"{printable(env.scenario_id)}: {args.policy} drove {args.steps} steps; "
          f"{files.records} FCD records -> {files.fcd}; replay: sumo-gui -c {files.sumocfg}",
          file=sys.stderr)
    return 0
