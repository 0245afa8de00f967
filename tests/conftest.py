"""Shared fixtures: the bundled real WOMD scenes (and ../shared data when present), their
converted bundles (converted once per session), and helpers used by several test modules."""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from converters import load_scene

ROOT = Path(__file__).resolve().parents[1]
WOMD_DIR = ROOT / "data" / "womd"
SCENARIONET_DIR = ROOT / "data" / "scenarionet"
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


class BundledNetworks:
    """Networks folders holding converted bundles of the bundled scenes: the WOMD scenes of
    ``data/womd/<id>.tfrecord`` and the ScenarioNet scenes of ``data/scenarionet/<id>.pkl``.

    ``bundled_networks(*scenario_ids)`` is a networks folder holding the bundles of exactly
    those scenes (the bundled WOMD scenes when none is named), marked as ``convert``'s (as a
    folder that :func:`~magail_sumo.env.scene_specs.scene_specs` converted into is);
    ``bundled_networks.bundle(scenario_id)`` is one scene's bundle folder. Each scene is
    converted once per session, by ``scene_specs`` itself (baseline run skipped, source
    recorded), and each set of scenes is laid out once (bundles copied).

    The folders are shared by every test that asks for them: read them, never write into them
    (the session ends with an error naming the files that changed). A test that writes into
    its networks folder (converts more scenes into it, say) copies one first:
    ``shutil.copytree(bundled_networks(sid), tmp_path / "nets")``.
    """

    def __init__(self, tmp_path_factory) -> None:
        self._factory = tmp_path_factory
        self._converted: Path | None = None
        self._bundles: dict[str, Path] = {}
        self._sets: dict[tuple[str, ...], Path] = {}
        self._digests: dict[Path, dict[str, str]] = {}

    def bundle(self, scenario_id: str) -> Path:
        """The bundle folder of one bundled scene (converted on first use)."""
        from converters.sumo.scenario import claim_networks_dir
        from magail_sumo.env.scene_specs import scene_specs

        if scenario_id not in self._bundles:
            path = WOMD_DIR / f"{scenario_id}.tfrecord"
            if not path.is_file():
                path = SCENARIONET_DIR / f"{scenario_id}.pkl"
            assert path.is_file(), f"{scenario_id} is not a bundled scene"
            if self._converted is None:
                self._converted = claim_networks_dir(self._factory.mktemp("bundled_scenes"))
            (spec,) = scene_specs([str(path)], self._converted)
            folder = self._bundles[scenario_id] = Path(spec.bundle)
            self._digests[folder] = tree_digest(folder)
        return self._bundles[scenario_id]

    def __call__(self, *scenario_ids: str) -> Path:
        from converters.sumo.scenario import claim_networks_dir

        key = tuple(sorted(set(scenario_ids))) or BUNDLED_WOMD
        if key not in self._sets:
            root = self._factory.mktemp("networks")
            for sid in key:
                shutil.copytree(self.bundle(sid), root / sid)
            claim_networks_dir(root)
            self._sets[key] = root
            self._digests[root] = tree_digest(root)
        return self._sets[key]

    def changed(self) -> list[str]:
        """Files added, changed or removed in the folders handed out since."""
        out = []
        for root, before in self._digests.items():
            after = tree_digest(root)
            out += [str(root / p) for p in sorted(set(before) | set(after))
                    if before.get(p) != after.get(p)]
        return out


def tree_digest(root: Path) -> dict[str, str]:
    """Relative path -> SHA-256 of every file under ``root`` ("dir" for folders)."""
    out = {}
    for dirpath, dirs, files in os.walk(root):
        for d in dirs:
            out[os.path.relpath(os.path.join(dirpath, d), root)] = "dir"
        for f in files:
            p = os.path.join(dirpath, f)
            out[os.path.relpath(p, root)] = hashlib.sha256(Path(p).read_bytes()).hexdigest()
    return out


#: The scenario ids of the bundled WOMD scenes (data/womd/<id>.tfrecord).
BUNDLED_WOMD = tuple(sorted(p.stem for p in WOMD_DIR.glob("*.tfrecord")))


@pytest.fixture(scope="session")
def bundled_networks(tmp_path_factory):
    """:class:`BundledNetworks`: ``bundled_networks(sid, ...)`` is a shared, read-only
    networks folder with the converted bundles of those bundled scenes, converted once per
    session."""
    nets = BundledNetworks(tmp_path_factory)
    yield nets
    changed = nets.changed()
    assert not changed, ("a test wrote into a shared bundled_networks folder (copy it "
                         f"first): {changed[:10]}")


@pytest.fixture(scope="session", params=real_scene_files(), ids=lambda p: p.stem)
def real_scene_file(request) -> Path:
    return request.param


@pytest.fixture(scope="session")
def real_scene(real_scene_file):
    return load_scene(real_scene_file)


def killed_worker_ends_the_env(venv) -> None:
    """With no replacement allowed (``max_restarts=0``): killing worker 0's process makes the
    next step raise ``VecEnvWorkerError`` saying it died; the env is closed after."""
    import os
    import signal

    import numpy as np
    import pytest

    from magail_sumo.env.vec_env import VecEnvWorkerError

    try:
        venv.reset()
        os.kill(venv._handles[0].pid, signal.SIGKILL)
        with pytest.raises(VecEnvWorkerError, match="died"):
            venv.step(np.zeros((venv.num_envs, 2), np.float32))
    finally:
        venv.close()


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


class PartialPolicy:
    """A policy that acts for every other agent only, plus one made-up agent (to see what the
    env and evaluation do with missing and unknown actions)."""

    def act(self, observations):
        import numpy as np

        names = sorted(observations)
        out = {n: np.zeros(2, np.float32) for n in names[::2]}
        out["no-such-agent"] = np.zeros(2, np.float32)
        return out


def peak_memory(fn):
    """``(fn(), peak bytes allocated while it ran)``, measured with ``tracemalloc``: it records
    an allocation's full size even when its pages are never touched, so a regression that
    allocates a size a file claims is caught without the machine spending the memory."""
    import tracemalloc

    tracemalloc.start()
    try:
        result = fn()
        return result, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@contextlib.contextmanager
def small_tmpfs(path: Path, size: str):
    """A real tmpfs of ``size`` (``"256k"``) mounted on the new folder ``path`` for the block (a
    full disk without mocking anything); the test is skipped where mounting is not allowed
    (not root, no mount capability)."""
    path.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                       capture_output=True)
    if r.returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield path
    finally:
        subprocess.run(["umount", str(path)], capture_output=True)


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
