"""Pre-flight checks of a training config that need the machine or the scene files (device
available, scene files readable, ``env.start_step`` / ``env.min_history`` inside every scene),
run before any set-up; the config's own ranges are checked when it loads
(:mod:`magail_sumo.training.config`)."""

from __future__ import annotations

from os import PathLike

import torch

from converters.scene_files import read_record
from magail_sumo.config import ConfigError, FieldError, check, show
from magail_sumo.env.scene_pool import is_city, resolve_pool, start_problem
from magail_sumo.errors import MagailSumoError

from .config import TrainConfig


def check_device(device: str) -> None:
    """:class:`FieldError` unless ``device`` exists on this machine."""
    dev = torch.device(device)
    if dev.type == "cuda":
        n = torch.cuda.device_count() if torch.cuda.is_available() else 0
        check(n > 0, "device", f"{show(device)}: no CUDA device available")
        check(dev.index is None or dev.index < n, "device",
              f"{show(device)}: not available ({n} CUDA device{'s' if n != 1 else ''}: "
              f"cuda:0{f' .. cuda:{n - 1}' if n > 1 else ''})")
    elif dev.type == "mps":
        check(torch.backends.mps.is_available(), "device", f"{show(device)}: not available")


def check_train_config(cfg: TrainConfig, source: str | PathLike | None = None) -> None:
    """Checks of ``cfg`` that need this machine and the scene files, before any set-up:
    the device exists, every scene file is readable and ``env.start_step`` (with
    ``env.start_window: random``, ``env.min_history``) leaves at least one step in each of its
    scenes. :class:`ConfigError` naming ``source`` (the config file) and
    the key."""
    from pathlib import Path

    where = f"{source}: " if source is not None else ""
    try:
        check_device(cfg.device)
    except FieldError as exc:
        raise ConfigError(f"{where}{exc.key}: {exc.problem}") from None
    if cfg.algorithm == "bc":
        return
    if cfg.algorithm == "gameformer":
        for i, f in enumerate(cfg.scenes.files):
            if not set("*?[") & set(str(f)) and not Path(f).exists():
                raise ConfigError(f"{where}scenes.files[{i}]: {show(f, 200)}: no such file")
        return

    checked = []
    for i, f in enumerate(cfg.scenes.files):
        key = f"scenes.files[{i}]"
        if not set("*?[") & set(str(f)) and not Path(f).exists():
            raise ConfigError(f"{where}{key}: {show(f, 200)}: no such file")
        skipped: list = []
        refs = resolve_pool([f], skipped)
        if not refs:
            why = skipped[0].reason if skipped else "no scene"
            raise ConfigError(f"{where}{key}: cannot read the scenes ({show(why, 200)[1:-1]})")
        if cfg.discriminator.kind == "transformer" and cfg.algorithm != "sac" \
                and any(is_city(r) for r in refs):
            raise ConfigError(f"{where}discriminator.kind: 'transformer' judges all vehicles of "
                              f"a worker step as one set, not a city's local neighbourhoods "
                              f"({key} is a city scenario); use 'decomposed' (each vehicle "
                              "with its K nearest within R m) or 'mlp'")
        checked.extend(r for r in refs[:max(0, 32 - len(checked))] if not is_city(r))
    # a small pool is read now: a start past every scene is a config mistake (in a larger
    # pool, or next to usable scenes, such a scene is skipped at run time)
    problems = []
    for ref in checked:
        try:
            scene = read_record(ref)
        except (MagailSumoError, OSError, ValueError):
            continue  # skipped at run time, with its reason
        problem = start_problem(scene, cfg.env)
        if problem is None:
            return
        problems.append(f"{problem} of {ref}")
    if problems:
        key_start = "min_history" if cfg.env.start_window == "random" else "start_step"
        raise ConfigError(f"{where}env.{key_start}: {problems[0]}")
