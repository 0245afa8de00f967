"""SumoDrivingEnv on real converted scenes with real SUMO: API, actions (missing and unknown
ones too), fidelity, events, and where agents end (``env.end_of_life``)."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from conftest import ROOT, PartialPolicy, WOMD_DIR
from converters import load_scene
from converters.sumo.bundle import BundleError
from magail_sumo.config import ConfigError
from magail_sumo.env import REPLAY_LIMITS, EnvConfig, SumoDrivingEnv, expert_actions
from magail_sumo.env.collision import first_overlap
from magail_sumo.env.events import StopLines, off_road

SCENES = ("850c48d8bbfa008f", "637f20cafde22ff8", "2831b6fde0420b0d")


@pytest.fixture(scope="module")
def bundles(bundled_networks):
    return {sid: (load_scene(WOMD_DIR / f"{sid}.tfrecord"), bundled_networks.bundle(sid))
            for sid in SCENES}


@pytest.mark.sumo
def test_parallel_api(bundles):
    scene, folder = bundles["850c48d8bbfa008f"]
    env = SumoDrivingEnv(scene, folder, EnvConfig(max_steps=40), render_mode="rgb_array")
    parallel_api_test(env, num_cycles=40)
    env.reset(seed=1)
    frame = env.render()
    assert frame.shape == (512, 512, 3) and frame.dtype == np.uint8
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) >= 4  # map and boxes drawn
    env.close()


@pytest.mark.sumo
def test_random_episode(bundles):
    scene, folder = bundles["637f20cafde22ff8"]
    env = SumoDrivingEnv(scene, folder, EnvConfig(controlled=8, max_steps=60))
    obs, _ = env.reset(seed=3)
    assert 0 < len(env.agents) <= 8 and str(int(scene.tracks.id[scene.sdc_track_index])) in obs
    steps, reasons = 0, set()
    while env.agents:
        act = {a: env.action_space(a).sample() for a in env.agents}
        obs, rew, term, trunc, info = env.step(act)
        steps += 1
        for a, o in obs.items():
            assert env.observation_space(a).contains(o), a
        reasons |= {i["reason"] for a, i in info.items() if term[a] or trunc[a]}
    assert steps <= 60 and reasons and None not in reasons
    env.close()


@pytest.mark.sumo
def test_nan_and_out_of_range_actions_are_counted_and_clipped(bundles):
    scene, folder = bundles["637f20cafde22ff8"]
    env = SumoDrivingEnv(scene, folder, EnvConfig(controlled=3, terminate_on=()))
    env.reset(seed=0)
    a, b, c = env.agents[:3]
    before = env.agent_states()
    _, _, _, _, info = env.step({a: np.array([np.nan, 0.2]), b: np.array([5.0, -3.0])})
    after = env.agent_states()
    assert (info[a]["nan_actions"], info[a]["clipped_actions"]) == (1, 0)
    assert (info[b]["nan_actions"], info[b]["clipped_actions"]) == (0, 1)
    assert info[c]["nan_actions"] == 1  # missing action: zero action, counted
    i, j = after.names.index(b), before.names.index(b)
    dv = (after.state.speed[i] - before.state.speed[j]) / env.dt
    assert dv == pytest.approx(env.config.limits.max_accel)  # clipped to +1 = max accel
    assert np.isfinite(after.state.x).all()
    env.close()


@pytest.mark.sumo
@pytest.mark.parametrize("sid", SCENES)
def test_expert_actions_follow_the_log(bundles, sid):
    """Issue fidelity check: expert (inverse-dynamics) actions keep every controlled vehicle
    within 0.2 m of its recorded positions over its whole recorded life."""
    scene, folder = bundles[sid]
    tr = scene.tracks
    env = SumoDrivingEnv(scene, folder, EnvConfig(terminate_on=(), limits=REPLAY_LIMITS))
    env.reset(seed=0)
    worst, checked, ended, yaw_err = 0.0, 0, {}, []
    while env.agents:
        _, _, _, trunc, info = env.step(expert_actions(env))
        st = env.agent_states()
        left = [a for a in trunc if trunc[a]]
        ended.update({a: (env.t, info[a]["reason"]) for a in left})
        v = tr.valid[st.rows, env.t]
        err = np.hypot(st.state.x - tr.x[st.rows, env.t], st.state.y - tr.y[st.rows, env.t])[v]
        worst = max(worst, float(err.max(initial=0.0)))
        dyaw = np.angle(np.exp(1j * (st.state.yaw - tr.heading[st.rows, env.t])))[v]
        yaw_err.extend(np.abs(dyaw).tolist())
        checked += int(v.sum())
    env.close()
    assert worst < 0.2, worst
    assert np.percentile(yaw_err, 95) < np.radians(5), np.degrees(np.percentile(yaw_err, 95))
    assert checked > 100
    last = {str(int(tr.id[r])): int(np.flatnonzero(tr.valid[r])[-1]) for r in env._ctrl}
    assert {a: t for a, (t, _) in ended.items()} == {a: t for a, t in last.items() if t > 0}
    assert all(r in ("end_of_life", "end_of_episode") for _, r in ended.values())


def _polygon(x, y, yaw, length, width):
    c, s = np.cos(yaw), np.sin(yaw)
    u = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * 0.5 * np.array([length, width])
    return np.array([x, y]) + u @ np.array([[c, s], [-s, c]])


def _polygons_overlap(p, q) -> bool:
    """Reference: convex polygons overlap iff an edge pair crosses or one holds the other's corner."""
    def inside(pt, poly):
        e = np.roll(poly, -1, axis=0) - poly
        r = pt - poly
        cross = e[:, 0] * r[:, 1] - e[:, 1] * r[:, 0]
        return (cross >= -1e-9).all() or (cross <= 1e-9).all()

    def cross(a, b, c, d):
        o = lambda p1, p2, p3: np.sign((p2[0] - p1[0]) * (p3[1] - p1[1]) - (p2[1] - p1[1]) * (p3[0] - p1[0]))  # noqa: E731
        return o(a, b, c) != o(a, b, d) and o(c, d, a) != o(c, d, b)

    if any(inside(pt, q) for pt in p) or any(inside(pt, p) for pt in q):
        return True
    return any(cross(p[i], p[(i + 1) % 4], q[j], q[(j + 1) % 4]) for i in range(4) for j in range(4))


def test_collision_constructed_boxes():
    # 0/1 overlap head-on; 2 and 3 are diagonal neighbours whose bounding circles overlap but
    # SAT separates them; 4 is far away
    x = np.array([0.0, 4.0, 20.0, 23.2, 100.0])
    y = np.array([0.0, 0.5, 0.0, 3.2, 0.0])
    yaw = np.array([0.0, 0.3, np.pi / 4, np.pi / 4, 0.0])
    length = np.full(5, 4.5)
    width = np.full(5, 2.0)
    got = first_overlap(x, y, yaw, length, width, np.arange(5))
    assert got.tolist() == [1, 0, -1, -1, -1]


def test_collision_on_a_log_step(scene_637f):
    tr = scene_637f.tracks
    t = 10
    r = np.flatnonzero(tr.valid[:, t])
    args = (tr.x[r, t], tr.y[r, t], tr.heading[r, t].astype(float), tr.length[r, t].astype(float),
            tr.width[r, t].astype(float))
    got = first_overlap(*args, np.arange(len(r))) >= 0
    polys = [_polygon(*(a[i] for a in args)) for i in range(len(r))]
    ref = np.array([any(_polygons_overlap(polys[i], polys[j]) for j in range(len(r)) if j != i)
                    for i in range(len(r))])
    np.testing.assert_array_equal(got, ref)
    assert ref.any() and not ref.all()


def test_red_light_and_off_road_rules(scene_637f):
    lines = StopLines.build(scene_637f)
    red = np.flatnonzero(lines.red)
    assert red.size
    k = red[0]
    step, pt, d = int(lines.step[k]), lines.point[k], lines.direction[k]
    p0 = np.array([pt - 1.0 * d, pt - 1.0 * d, pt + 1.0 * d])
    p1 = np.array([pt + 1.0 * d, pt - 0.5 * d, pt + 2.0 * d])
    got = lines.red_crossings(step, p0, p1, 3.7)
    same_line = lines.line == lines.line[k]
    on_step = lines.step == step
    assert got.tolist() == [bool(lines.red[same_line & on_step].all()), False, False]
    assert off_road(np.array([1.0, 2.9]), 3.7, 1.0).tolist() == [False, True]


@pytest.mark.sumo
def test_missing_bundle_file(bundles, tmp_path):
    scene, folder = bundles["850c48d8bbfa008f"]
    with pytest.raises(BundleError, match=r"850c48d8bbfa008f\.sumocfg: bundle file not found"):
        SumoDrivingEnv(scene, tmp_path)


@pytest.mark.sumo
def test_seed_action_layout_expert_replay(bundles):
    """With the seed's (steer, throttle) layout the expert actions still follow the log."""
    scene, folder = bundles["850c48d8bbfa008f"]
    tr = scene.tracks
    env = SumoDrivingEnv(scene, folder, EnvConfig(terminate_on=(), limits=REPLAY_LIMITS,
                                                  action_layout="steer_throttle"))
    env.reset(seed=0)
    worst = 0.0
    while env.agents:
        env.step(expert_actions(env))
        st = env.agent_states()
        v = tr.valid[st.rows, env.t]
        err = np.hypot(st.state.x - tr.x[st.rows, env.t], st.state.y - tr.y[st.rows, env.t])[v]
        worst = max(worst, float(err.max(initial=0.0)))
    env.close()
    assert worst < 0.2


def _episodes(env, seeds, actions_seed: int = 0):
    """Every output of a few random-window episodes under seeded random actions."""
    rng = np.random.default_rng(actions_seed)
    out = []
    for seed in seeds:
        obs, infos = env.reset(seed=seed)
        out.append((env.start, obs, infos))
        while env.agents:
            acts = {a: rng.uniform(-0.6, 0.6, 2).astype(np.float32) for a in sorted(env.agents)}
            out.append(env.step(acts))
    return out


def _same(a, b, where="") -> None:
    if isinstance(a, dict):
        assert list(a) == list(b), where
        for k in a:
            _same(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and np.array_equal(a, b), where
    else:
        assert a == b, where


@pytest.mark.sumo
@pytest.mark.parametrize("sid", SCENES)
def test_episodes_without_the_sumo_mirror_are_the_same(bundles, sid):
    """``sumo_mirror: false`` (background log) plays the same episodes bit for bit —
    observations, terminations, truncations and infos, collisions and off-road included — while
    SUMO never starts."""
    cfg = dict(controlled="all", start_window="random", max_steps=40,
               terminate_on=("collision", "off_road"))
    runs = []
    for mirror in (True, False):
        scene, bundle = bundles[sid]
        env = SumoDrivingEnv(scene, bundle,
                             EnvConfig(**cfg, sumo_mirror=mirror))
        try:
            runs.append(_episodes(env, seeds=(0, 1, 2)))
            events = sum(bool(i.get("reason")) for st in runs[-1][1:] if len(st) == 5
                         for i in st[4].values())
            if not mirror:
                assert type(env._session).__name__ == "_NoMirror"
        finally:
            env.close()
    _same(runs[0], runs[1])
    assert events > 0  # agents did end on events and at the end of their tracks


def test_sumo_mirror_is_needed_with_sumo_background():
    from magail_sumo.config import FieldError

    with pytest.raises(FieldError, match="sumo_mirror"):
        EnvConfig(background="sumo", sumo_mirror=False)


# ---------------------------------------------------------------------- missing and unknown actions
SID = "850c48d8bbfa008f"  # the smallest bundled scene
SCENE = WOMD_DIR / f"{SID}.tfrecord"


def env_action_counts(bundle: str) -> dict:
    """Three env steps with actions missing for every other agent and one unknown agent."""
    from converters import load_scene
    from magail_sumo.env import EnvConfig, SumoDrivingEnv

    env = SumoDrivingEnv(load_scene(SCENE), bundle, EnvConfig(controlled="all",
                                                              terminate_on=()))
    obs, _ = env.reset(seed=0)
    policy = PartialPolicy()
    expected_missing = 0
    for _ in range(3):
        expected_missing += len(env.agents) - len(sorted(env.agents)[::2])
        obs, *_ = env.step(policy.act({a: obs[a] for a in env.agents}))
    counts = dict(env.action_counts)
    env.close()
    return {"counts": counts, "expected_missing": expected_missing}


@pytest.mark.sumo
def test_env_counts_missing_and_unknown_actions(bundled_networks):
    from magail_sumo.workers import run_one

    res = run_one(env_action_counts, str(bundled_networks(SID) / SID), timeout_s=300)
    assert res.ok, res.reason
    counts = res.value["counts"]
    assert counts["missing"] == res.value["expected_missing"] > 0
    assert counts["unknown"] == 3 and counts["clipped"] == 0
    assert counts["nonfinite"] == counts["missing"]


def test_action_summary_words_the_counts():
    from magail_sumo.env.actions import action_summary

    assert action_summary({"missing": 0, "unknown": 0, "departed": 4, "nonfinite": 0,
                           "clipped": 0}) == ""
    line = action_summary({"missing": 12, "unknown": 3, "departed": 1, "nonfinite": 14,
                           "clipped": 1})
    assert line == ("policy gave no action for 12 agent-step(s) (those agents coasted: zero "
                    "acceleration and steering); 3 action(s) for unknown agents ignored; 2 "
                    "non-finite action(s) replaced by 0; 1 action(s) outside [-1, 1] clipped")


# ---------------------------------------------------------------------------------- env.end_of_life
# agents end at their log's last step in training; in evaluation every sim agent drives
# all 80 steps, as WOSAC simulates it (an agent removed earlier vanished from the others'
# world while its scored trajectory went on at constant velocity through them)
EOL_SID = "637f20cafde22ff8"
EOL_EARLY = "1603"  # a sim agent of EOL_SID whose recorded track ends at step 16


def _eol_env(end_of_life: bool):
    from converters import load_scene
    from magail_sumo.env import EnvConfig, SumoDrivingEnv

    scene = load_scene(WOMD_DIR / f"{EOL_SID}.tfrecord")
    return scene, SumoDrivingEnv(scene, ROOT / "networks" / EOL_SID, EnvConfig(
        controlled="all", start_step=10, max_steps=80, terminate_on=(), sumo_mirror=False,
        end_of_life=end_of_life))


@pytest.mark.sumo
@pytest.mark.parametrize("end_of_life", [True, False])
def test_agents_end_with_their_log_only_when_asked(end_of_life):
    from magail_sumo.evaluation.submission import sim_agent_ids

    scene, env = _eol_env(end_of_life)
    try:
        obs, _ = env.reset(seed=0)
        # the sim agents the env drives (the others are off the SUMO routes: log-replayed)
        sim = {str(int(i)) for i in sim_agent_ids(scene)} & set(env.agents)
        assert EOL_EARLY in sim and len(sim) >= 20
        ended, steps = {}, 0
        while env.agents:
            obs, _, terms, truncs, infos = env.step({n: np.zeros(2, np.float32) for n in obs})
            steps += 1
            for n in truncs:
                if truncs[n] or terms[n]:
                    ended[n] = (steps, infos[n]["reason"])
    finally:
        env.close()
    assert steps == 80
    if end_of_life:
        assert ended[EOL_EARLY] == (6, "end_of_life")  # log step 16 = 6 steps after step 10
    else:  # every sim agent drives to the episode's end
        assert all(ended[n][0] == 80 and ended[n][1] != "end_of_life" for n in sim)


@pytest.mark.sumo
def test_evaluation_keeps_every_sim_agent_to_the_horizon(scene_637f, env_configs):
    """Evaluation's env has end_of_life off: an agent whose log ends early has a driven
    (not constant-velocity) trajectory to the last step."""
    from magail_sumo.evaluation import methods

    ro = methods.simulate(scene_637f, "random", [0], seed=0, bundle_dir=ROOT / "networks" / EOL_SID)
    assert [c.end_of_life for c in env_configs] == [False]
    a = [int(i) for i in ro.object_id].index(int(EOL_EARLY))
    x, y = ro.x[0, a], ro.y[0, a]
    # random accelerations and steering: the path after the log's end (step 16: column 5 on)
    # is no straight line at constant speed
    jerk = np.hypot(np.diff(x[5:], 2), np.diff(y[5:], 2))
    assert np.isfinite(x).all() and (jerk > 1e-3).mean() > 0.5


def test_end_of_life_must_be_a_bool():
    from magail_sumo.config import from_dict
    from magail_sumo.env import EnvConfig

    with pytest.raises(ConfigError, match="end_of_life: expected true or false"):
        from_dict(EnvConfig, {"end_of_life": "no"})
