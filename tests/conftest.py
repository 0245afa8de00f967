"""Shared fixtures: the bundled real WOMD scenes (and ../shared data when present)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from converters import load_scene

ROOT = Path(__file__).resolve().parents[1]
WOMD_DIR = ROOT / "data" / "womd"
SHARED_WOMD = ROOT.parent / "shared" / "data" / "womd"

#: Counts from the dataset README (the official Waymo protos' parse of each scene).
EXPECTED = {
    "637f20cafde22ff8": {
        "scenario_id": "637f20cafde22ff8", "num_steps": 91,
        "tracks_by_type": {"vehicle": 70, "pedestrian": 10, "cyclist": 3, "other": 0},
        "valid_states": 4596,
        "map_features": {"lane": 199, "road_line": 59, "road_edge": 28, "stop_sign": 8,
                         "crosswalk": 4, "speed_bump": 3, "driveway": 0},
        "signal_states": 1092, "sdc_track_index": 82, "tracks_to_predict": 3,
    },
    "2831b6fde0420b0d": {
        "scenario_id": "2831b6fde0420b0d", "num_steps": 199,
        "tracks_by_type": {"vehicle": 19, "pedestrian": 0, "cyclist": 0, "other": 0},
        "valid_states": 1760,
        "map_features": {"lane": 231, "road_line": 34, "road_edge": 67, "stop_sign": 6,
                         "crosswalk": 4, "speed_bump": 4, "driveway": 0},
        "signal_states": 0, "sdc_track_index": 18, "tracks_to_predict": 0,
    },
    "850c48d8bbfa008f": {
        "scenario_id": "850c48d8bbfa008f", "num_steps": 91,
        "tracks_by_type": {"vehicle": 7, "pedestrian": 0, "cyclist": 0, "other": 0},
        "valid_states": 451,
        "map_features": {"lane": 85, "road_line": 26, "road_edge": 28, "stop_sign": 7,
                         "crosswalk": 3, "speed_bump": 1, "driveway": 0},
        "signal_states": 0, "sdc_track_index": 6, "tracks_to_predict": 0,
    },
}


def real_scene_files() -> list[Path]:
    """Bundled real scenes, plus any other real WOMD scene in ../shared when present."""
    files = sorted(WOMD_DIR.glob("*.tfrecord"))
    names = {f.name for f in files}
    if SHARED_WOMD.is_dir():
        files += sorted(f for f in SHARED_WOMD.glob("*.tfrecord") if f.name not in names)
    return files


@pytest.fixture(scope="session")
def scene_637f():
    return load_scene(WOMD_DIR / "637f20cafde22ff8.tfrecord")


@pytest.fixture(scope="session", params=real_scene_files(), ids=lambda p: p.stem)
def real_scene_file(request) -> Path:
    return request.param


@pytest.fixture(scope="session")
def real_scene(real_scene_file):
    return load_scene(real_scene_file)


def roll_random(venv, steps: int, seed: int = 0, hook=None) -> list:
    """Observations of a vector env over a reset and ``steps`` steps of uniform random actions
    (seeded); ``hook(t, venv)`` runs before step ``t`` (to inject a fault, grab the state)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    out = [venv.reset()]
    for t in range(steps):
        if hook is not None:
            hook(t, venv)
        out.append(venv.step(rng.uniform(-1, 1, (venv.num_envs, 2)).astype(np.float32))[0])
    return out


@pytest.fixture
def env_configs(monkeypatch) -> list:
    """The :class:`~magail_sumo.env.EnvConfig` of every ``SumoDrivingEnv`` built while the test
    runs, in order (e.g. to see what evaluation builds its env with)."""
    from magail_sumo.env import driving_env

    seen: list = []
    init = driving_env.SumoDrivingEnv.__init__

    def spy(self, scene, bundle, config=None, render_mode=None):
        seen.append(config)
        init(self, scene, bundle, config, render_mode)

    monkeypatch.setattr(driving_env.SumoDrivingEnv, "__init__", spy)
    return seen


def tiny_checkpoint(path, env: dict):
    """A 0-update PPO checkpoint file ``path`` of a tiny policy trained in env settings ``env``
    (a config dict): for tests of what a checkpoint carries into evaluation."""
    import torch

    from magail_sumo.config import from_dict, to_dict
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.trainer import CHECKPOINT_FORMAT, make_policy

    cfg = from_dict(TrainConfig, {"seed": 1, "env": env,
                                  "policy": {"actor_hidden": [8], "critic_hidden": [8]}})
    torch.manual_seed(1)
    torch.save({"format": CHECKPOINT_FORMAT, "update": 0, "config": to_dict(cfg),
                "policy": make_policy(cfg).state_dict()}, path)
    return path
