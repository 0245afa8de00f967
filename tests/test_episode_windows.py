"""Episode windows: random start steps with the log as history, evaluation-aligned training.

Real SUMO on the bundled 20 s scene 2831b6fde0420b0d (199 steps) and 637f20cafde22ff8."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from conftest import ROOT, WOMD_DIR
from converters import load_scene
from magail_sumo.config import ConfigError, FieldError, load_config
from magail_sumo.env import REPLAY_LIMITS, EnvConfig, SumoDrivingEnv, expert_actions
from magail_sumo.env.config import draw_start, window_starts
from magail_sumo.env.log_actions import training_actions
from magail_sumo.env.scene_specs import scene_specs
from magail_sumo.env.vec_env import MultiSceneVecEnv, episode_rng, max_concurrent_agents
from magail_sumo.sensors.observation import observation_names
from magail_sumo.training.config import TrainConfig
from magail_sumo.training.preflight import check_train_config
from magail_sumo.training.trainer import load_checkpoint, train
from test_training import setup  # noqa: F401 - the resume test's tiny run (fixture)

LONG = "2831b6fde0420b0d"  # 199 steps, no tracks to predict
SHORT = "637f20cafde22ff8"  # 91 steps, 3 tracks to predict


@pytest.fixture(scope="module")
def long_spec(bundled_networks):
    return scene_specs([WOMD_DIR / f"{LONG}.tfrecord"], bundled_networks(LONG))


@pytest.fixture(scope="module")
def long_scene(long_spec):
    return load_scene(WOMD_DIR / f"{LONG}.tfrecord"), long_spec[0].bundle


def _windows(**kw) -> EnvConfig:
    return EnvConfig(**{"start_window": "random", "min_history": 10, "terminate_on": (), **kw})


# ------------------------------------------------------------------------------ config
@pytest.mark.parametrize("kw, key, words", [
    ({"start_window": "sliding"}, "start_window", "must be one of ['fixed', 'random']"),
    ({"min_history": -1}, "min_history", "must be an int >= 0"),
    ({"start_window": "random"}, "max_steps", "must be set with start_window 'random'"),
    ({"start_window": "random", "max_steps": 80, "start_step": 10}, "start_step",
     "is not used with start_window 'random'"),
    ({"controlled": "scoring"}, "controlled", "'scored'"),
])
def test_bad_window_config_is_refused(kw, key, words):
    with pytest.raises(FieldError) as exc:
        EnvConfig(**kw)
    assert exc.value.key == key and words in exc.value.problem
    assert "\n" not in str(exc.value)


def test_window_config_from_yaml_and_shipped_config(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("env:\n  start_window: random\n  max_steps: null\n")
    with pytest.raises(ConfigError, match=r"c\.yaml: env\.max_steps: must be set"):
        load_config(p, TrainConfig)
    womd3 = ROOT / "configs" / "experiments" / "womd3"
    cfg = load_config(womd3 / "magail_windows.yaml", TrainConfig)
    scratch = load_config(womd3 / "magail_scratch.yaml", TrainConfig)
    assert (cfg.env.start_window, cfg.env.min_history, cfg.env.max_steps) == ("random", 10, 80)
    assert replace(cfg, env=scratch.env) == scratch  # otherwise magail_scratch.yaml


def test_min_history_past_the_scene_refused():
    scene = str(WOMD_DIR / f"{SHORT}.tfrecord")
    cfg = TrainConfig(scenes=replace(TrainConfig().scenes, files=(scene,)),
                      env=_windows(max_steps=80, min_history=90))
    with pytest.raises(ConfigError, match=r"env\.min_history: 90 leaves no step .*91 steps"):
        check_train_config(cfg, "c.yaml")
    check_train_config(replace(cfg, env=_windows(max_steps=80, min_history=89)))


def test_window_start_rule():
    w = _windows(max_steps=80)
    assert window_starts(w, 199) == (10, 118)  # a 20 s scene: 109 windows of 80 steps
    assert window_starts(w, 91) == (10, 10)  # WOMD: evaluation's window (current step 10)
    assert window_starts(w, 50) == (10, 10)  # too short: history kept, episode to the log's end
    assert window_starts(w, 6) == (4, 4)
    assert window_starts(EnvConfig(start_step=300), 91) == (90, 90)
    starts = {draw_start(w, 199, episode_rng(7, e)) for e in range(200)}
    assert min(starts) >= 10 and max(starts) <= 118 and len(starts) > 50
    assert draw_start(w, 199, episode_rng(7, 3)) == draw_start(w, 199, episode_rng(7, 3))


# ------------------------------------------------------------------------------ env
@pytest.mark.sumo
def test_random_window_lasts_max_steps(long_scene):
    scene, folder = long_scene
    env = SumoDrivingEnv(scene, folder, _windows(max_steps=30))
    try:
        starts = []
        for seed in (0, 1, 2):
            env.reset(seed=seed)
            start = env.start
            assert env.t == start and 10 <= start <= 199 - 1 - 30
            steps = 0
            while env.agents:
                env.step({a: np.zeros(2, np.float32) for a in env.agents})
                steps += 1
            assert steps == 30 and env.t == start + 30
            starts.append(start)
        env.reset(seed=1)
        assert env.start == starts[1]  # the reset seed fixes the window
        assert len(set(starts)) > 1
    finally:
        env.close()


@pytest.mark.sumo
def test_first_observation_carries_the_logs_previous_action(long_scene):
    """The window's first observation has the previous action the expert data has at that step
    (the recorder's replay: expert_actions under REPLAY_LIMITS from step 0, converted to the
    training scale) for agents mid-track, and 0 for one whose track starts there."""
    scene, folder = long_scene
    tr = scene.tracks
    env = SumoDrivingEnv(scene, folder, EnvConfig(controlled="all", terminate_on=(),
                                                  limits=REPLAY_LIMITS))
    routes = np.sort(env.bundle.sumo_rows)
    first = np.argmax(tr.valid[routes], axis=1)
    t0 = int(min(f for f in first if f >= 10))  # a route vehicle appears here (50)
    newcomer = str(int(tr.id[routes[first == t0][0]]))
    train_limits = EnvConfig().limits
    try:  # the expert recording's replay up to t0 (magail_sumo.expert.record)
        env.reset(seed=0)
        while env.t < t0:
            acts = expert_actions(env)
            env.step(acts)
            raw = np.stack(list(acts.values())).astype(np.float64)
            expert_prev = dict(zip(acts, training_actions(raw, train_limits)[0]))
    finally:
        env.close()
    names = observation_names(EnvConfig().observation)
    prev = [names.index("prev_accel"), names.index("prev_steer")]
    win = SumoDrivingEnv(scene, folder, EnvConfig(controlled="all", max_steps=5))
    try:
        obs, _ = win.reset(seed=0, options={"start_step": t0})
        assert win.t == win.start == t0 and newcomer in obs
        mid = [a for a in obs if tr.valid[np.flatnonzero(tr.id == int(a))[0], t0 - 1]]
        assert len(mid) >= 5
        for a in mid:
            np.testing.assert_array_equal(obs[a][prev], expert_prev[a], err_msg=a)
        assert np.abs(np.stack([obs[a][prev] for a in mid])).max() > 0.05
        assert np.array_equal(obs[newcomer][prev], [0.0, 0.0])
        # an episode from step 0 has no history: every previous action is 0
        obs0, _ = win.reset(seed=0)
        assert win.start == 0 and all(np.all(o[prev] == 0) for o in obs0.values())
        with pytest.raises(ValueError, match=r"start_step: must be an int in \[0, 197\]"):
            win.reset(options={"start_step": 198})
    finally:
        win.close()


@pytest.mark.sumo
def test_k_nearest_and_scored_use_the_episode_start(long_scene):
    scene, folder = long_scene
    tr = scene.tracks
    env = SumoDrivingEnv(scene, folder, EnvConfig(controlled=3, max_steps=5))
    routes = env.bundle.sumo_rows
    sdc = scene.sdc_track_index

    def nearest(t):
        d = np.hypot(tr.x[routes, t] - tr.x[sdc, t], tr.y[routes, t] - tr.y[sdc, t])
        d = np.where(tr.valid[routes, t], d, np.inf)
        d[routes == sdc] = -1
        return {str(int(tr.id[r])) for r in routes[np.argsort(d, kind="stable")[:3]]}

    try:
        got = {}
        for t in (10, 150):
            obs, _ = env.reset(seed=0, options={"start_step": t})
            got[t] = set(obs)
            assert got[t] == nearest(t) and set(env.possible_agents) >= got[t]
            for a in obs:
                assert env.observation_space(a).contains(obs[a])
        assert got[10] != got[150]
    finally:
        env.close()
    short = load_scene(WOMD_DIR / f"{SHORT}.tfrecord")
    env = SumoDrivingEnv(short, ROOT / "networks" / SHORT,
                         EnvConfig(controlled="scored", max_steps=3))
    try:
        obs, _ = env.reset(seed=0, options={"start_step": short.current_time_index})
        scored = [short.sdc_track_index] + [p.track_index for p in short.tracks_to_predict]
        # the SDC and two vehicles to predict; the pedestrian to predict is no route vehicle
        want = {str(int(short.tracks.id[i])) for i in scored if i in env.bundle.sumo_rows}
        assert len(want) == 3 and str(int(short.tracks.id[short.sdc_track_index])) in want
        assert set(env.possible_agents) == want and set(obs) == want
    finally:
        env.close()


# ------------------------------------------------------------------------------ vector env
@pytest.mark.sumo
def test_vec_env_window_starts_are_seeded_per_episode_and_restored(long_spec):
    cfg = _windows(max_steps=5, controlled=4)
    venv = MultiSceneVecEnv(long_spec, cfg, seed=11)
    other = None
    try:
        venv.reset()
        starts = [venv.get_attr("start", [0])[0]]
        rng = np.random.default_rng(0)
        for _ in range(12):
            venv.step(rng.uniform(-1, 1, (venv.num_envs, 2)))
            s = venv.get_attr("start", [0])[0]
            if venv.episodes >= len(starts):
                starts.append(s)
        assert len(starts) >= 3
        assert starts == [draw_start(cfg, 199, episode_rng(11, e)) for e in range(len(starts))]
        assert len(set(starts)) > 1 and all(10 <= s <= 199 - 1 - 5 for s in starts)
        assert venv.slots == [4]  # K agents at most, whatever the window
        state = venv.get_state()
        acts = rng.uniform(-1, 1, (venv.num_envs, 2))
        obs = venv.step(acts)[0]
        other = MultiSceneVecEnv(long_spec, cfg, seed=11)
        other.reset()
        other.set_state(state)  # exact resume: the same window, the same simulation
        assert other.get_attr("start", [0])[0] == starts[-1]
        assert np.array_equal(other.step(acts)[0], obs)
    finally:
        venv.close()
        if other is not None:
            other.close()


@pytest.mark.sumo
def test_slots_cover_every_window(long_scene):
    scene, folder = long_scene
    # short windows: the first one (steps 10-12) has more agents than steps 0-2 had
    env = SumoDrivingEnv(scene, folder, _windows(max_steps=2))
    try:
        slots = max_concurrent_agents(env)
        for t in range(10, 197, 9):
            env.reset(seed=0, options={"start_step": t})
            most = len(env.agents)
            for _ in range(2):
                if not env.agents:
                    break
                env.step({a: np.zeros(2, np.float32) for a in env.agents})
                most = max(most, len(env.agents))
            assert most <= slots, t
    finally:
        env.close()


# ------------------------------------------------------------------------------ training
@pytest.mark.sumo
def test_resume_with_random_windows_continues_exactly(setup):  # noqa: F811
    root, cfg = setup
    cfg = replace(cfg, env=replace(cfg.env, start_window="random", min_history=10,
                                   max_steps=30))
    straight = train(cfg, run_dir=root / "w_straight", log=lambda s: None)
    half = train(replace(cfg, updates=2), run_dir=root / "w_split", log=lambda s: None)
    resumed = train(cfg, resume=half, log=lambda s: None)
    a = load_checkpoint(straight / "checkpoints" / "latest.pt")
    b = load_checkpoint(resumed / "checkpoints" / "latest.pt")
    assert a["update"] == b["update"] == 4 and a["num_timesteps"] == b["num_timesteps"]
    for key in ("policy", "discriminator"):
        assert a[key].keys() == b[key].keys()
        for k in a[key]:
            assert torch.equal(torch.as_tensor(a[key][k]), torch.as_tensor(b[key][k])), (key, k)
    assert a["env_state"][0][0] >= 1  # the run went through more than one window
