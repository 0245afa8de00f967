"""The batched core (``BatchedSceneEnv``): each of its worlds runs exactly as a single-world
``SumoDrivingEnv`` of the scene with the same config and the same actions, on the real WOMD
and ScenarioNet scenes in data/ (15; not the GPUDrive JSON file), in an evaluation config
and in a training config with every event ending agents, the gap guard and the optional
sensors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from converters import load_scene
from magail_sumo.env import EnvConfig, SumoDrivingEnv
from magail_sumo.env.batched import BatchedSceneEnv, world_name
from magail_sumo.env.guard import GuardConfig
from magail_sumo.sensors.config import ObservationConfig
from magail_sumo.sensors.worlds import SHARED, BoxGroups

ROOT = Path(__file__).resolve().parents[1]
SCENES = sorted((ROOT / "data" / "womd").glob("*.tfrecord")) + \
    sorted((ROOT / "data" / "scenarionet").glob("*.pkl"))
WORLDS = 3

CONFIGS = {
    # what evaluation runs: every route vehicle from the current step, nobody ends early
    "evaluation": EnvConfig(controlled="all", start_step=10, max_steps=40, terminate_on=(),
                            end_of_life=False, sumo_mirror=False),
    # training-like: every event ends an agent, guard, leader, route command and look-ahead,
    # route-relative control, WOSAC's road-edge rule
    "training": EnvConfig(controlled="all", start_step=10, max_steps=40, sumo_mirror=False,
                          action_layout="accel_offset", off_road_rule="road_edge",
                          guard=GuardConfig(kind="gap"),
                          observation=ObservationConfig(command=True, route_points=(10.0, 30.0),
                                                        leader=True)),
}


def action(world: int, t: int, agent: str) -> np.ndarray:
    """A deterministic action that differs by world, step and agent (brakes hard now and
    then, so worlds drift apart and some agents collide or leave the road)."""
    k = int(agent) % 97
    a = np.sin(0.37 * t + 1.3 * world + 0.11 * k)
    return np.array([a if (t + k + world) % 7 else -1.0, 0.6 * np.cos(0.23 * t + world + k)],
                    np.float32)


def run_single(scene, bundle, cfg, world: int) -> dict:
    """Log step -> agent -> (obs, reward, term, trunc, info) of one single-world episode."""
    env = SumoDrivingEnv(scene, bundle, cfg)
    out: dict = {}
    obs, infos = env.reset(seed=0)
    out[env.t] = {a: (obs[a], None, None, None, infos[a]) for a in obs}
    try:
        while env.agents:
            acts = {a: action(world, env.t, a) for a in env.agents}
            obs, rew, term, trunc, infos = env.step(acts)
            out.setdefault(env.t, {}).update(
                {a: (obs[a], rew[a], term[a], trunc[a], infos[a]) for a in obs})
    finally:
        env.close()
    return out


def run_batched(scene, bundle, cfg) -> list[dict]:
    env = BatchedSceneEnv(scene, bundle, cfg, worlds=WORLDS)
    outs: list[dict] = [{} for _ in range(WORLDS)]

    def keep(obs, rew, term, trunc, infos):
        for w, d in enumerate(env.split(obs)):
            for a, o in d.items():
                n = world_name(w, a)
                outs[w].setdefault(env.t, {})[a] = (
                    o, None if rew is None else rew[n], None if term is None else term[n],
                    None if trunc is None else trunc[n], infos[n])

    obs, infos = env.reset(seed=0)
    keep(obs, None, None, None, infos)
    try:
        while env.agents:
            per_world = [{a: action(w, env.t, a) for a in d}
                         for w, d in enumerate(env.split(dict.fromkeys(env.agents)))]
            keep(*env.step(env.merge(per_world)))
    finally:
        env.close()
    return outs


@pytest.mark.parametrize("config", sorted(CONFIGS))
@pytest.mark.parametrize("scene_file", SCENES, ids=lambda p: p.stem)
def test_each_world_runs_as_the_single_env(scene_file, config, bundled_networks):
    scene = load_scene(scene_file)
    bundle = bundled_networks.bundle(scene_file.stem)
    cfg = CONFIGS[config]
    batched = run_batched(scene, bundle, cfg)
    ended = 0
    for w in range(WORLDS):
        single = run_single(scene, bundle, cfg, w)
        # the single env skips log steps nobody is live in; the batched one idles through
        got = {t: d for t, d in batched[w].items() if d}
        assert sorted(got) == sorted(single), f"world {w}: other log steps"
        for t, agents in single.items():
            assert sorted(got[t]) == sorted(agents), f"world {w} step {t}: other agents"
            for a, (o, r, te, tr, info) in agents.items():
                bo, br, bte, btr, binfo = got[t][a]
                np.testing.assert_array_equal(bo, o, err_msg=f"world {w} step {t} agent {a}")
                assert (br, bte, btr) == (r, te, tr), f"world {w} step {t} agent {a}"
                assert binfo == info, f"world {w} step {t} agent {a}"
                ended += bool(te) or bool(info["events"] and any(info["events"].values()))
    if config == "training" and scene_file.stem == "637f20cafde22ff8":
        assert ended > 0  # the comparison covered agents that met events


@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_array_api_gives_the_dict_api_step(config, bundled_networks):
    """``reset_arrays`` / ``step_arrays`` give the observations, rewards, terminations,
    truncations and events the dict API gives, row for row."""
    scene_file = SCENES[0]
    scene = load_scene(scene_file)
    bundle = bundled_networks.bundle(scene_file.stem)
    cfg = CONFIGS[config]
    dicts = run_batched(scene, bundle, cfg)
    env = BatchedSceneEnv(scene, bundle, cfg, worlds=WORLDS)
    st = env.reset_arrays(seed=0)
    per = env.per_world
    compared = 0
    while not env.finished:
        rows = np.flatnonzero(st.live)
        acts = np.full((len(env.fleet), 2), np.nan, np.float32)  # not live: ignored
        for k in rows.tolist():
            acts[k] = action(k // per, env.t, env.world_agents[k % per])
        stepped = rows
        st = env.step_arrays(acts)
        for k in np.flatnonzero(st.observed).tolist():
            w, a = k // per, env.world_agents[k % per]
            o, r, te, tr, info = dicts[w][env.t][a]
            np.testing.assert_array_equal(st.observations[k], o)
            if k in stepped:
                assert (st.rewards[k], st.terminated[k], st.truncated[k]) == (r, te, tr)
                assert {e: bool(v[k]) for e, v in st.events.items()} == info["events"]
                compared += 1
    assert compared > 0 and env.action_counts["nonfinite"] == 0
    with pytest.raises(ValueError, match="actions must be"):
        env.step_arrays(np.zeros((1, 2)))
    env.close()


def test_single_env_array_api_gives_its_dict_step(bundled_networks):
    """A single-world ``SumoDrivingEnv``'s array API gives its dict API's observations and
    outcomes (the training config: agents end on events)."""
    scene_file = SCENES[0]
    scene = load_scene(scene_file)
    bundle = bundled_networks.bundle(scene_file.stem)
    cfg = CONFIGS["training"]
    dicts = run_single(scene, bundle, cfg, 0)
    env = SumoDrivingEnv(scene, bundle, cfg)
    st = env.reset_arrays(seed=0)
    names = env.fleet.names
    for k in np.flatnonzero(st.observed).tolist():
        np.testing.assert_array_equal(st.observations[k], dicts[env.t][names[k]][0])
    ended = 0
    while not env.finished:
        rows = np.flatnonzero(st.live)
        acts = np.zeros((len(env.fleet), 2), np.float32)
        for k in rows.tolist():
            acts[k] = action(0, env.t, names[k])
        st = env.step_arrays(acts)
        for k in np.flatnonzero(st.observed).tolist():
            o, r, te, tr, info = dicts[env.t][names[k]]
            np.testing.assert_array_equal(st.observations[k], o)
            if k in rows:
                assert (st.rewards[k], st.terminated[k], st.truncated[k]) == (r, te, tr)
                ended += bool(te or tr)
    assert ended > 0
    env.close()


def test_worlds_differ_and_stay_apart(bundled_networks):
    """Different actions give different worlds, and one world's agents are not in another's
    lidar: the same agent sees the same when its world's actions are the same."""
    scene_file = SCENES[0]
    scene = load_scene(scene_file)
    env = BatchedSceneEnv(scene, bundled_networks.bundle(scene_file.stem),
                          CONFIGS["evaluation"], worlds=2)
    obs, _ = env.reset(seed=0)
    for _ in range(15):  # world 0 brakes, world 1 accelerates
        acts = {a: np.array([-1.0 if a.startswith("0/") else 1.0, 0.0], np.float32)
                for a in env.agents}
        obs, *_ = env.step(acts)
    w0, w1 = env.split(obs)
    assert set(w0) == set(w1)
    assert any(not np.array_equal(w0[a], w1[a]) for a in w0)
    env.close()


def test_refuses_what_it_does_not_run(bundled_networks):
    scene_file = SCENES[0]
    bundle = bundled_networks.bundle(scene_file.stem)
    with pytest.raises(ValueError, match="sumo_mirror: true"):
        BatchedSceneEnv(scene_file, bundle, EnvConfig(), worlds=2)
    with pytest.raises(ValueError, match="worlds must be an int >= 1"):
        BatchedSceneEnv(scene_file, bundle, EnvConfig(sumo_mirror=False), worlds=0)


def test_box_groups_candidates():
    world = np.array([0, 0, 1, SHARED, 1, SHARED, 0])
    g = BoxGroups.of(world, 2)
    cand = g.candidates(np.array([0, 2, 6]))
    np.testing.assert_array_equal(cand, [[0, 1, 6, 3, 5], [2, 4, 3, 5, -1], [0, 1, 6, 3, 5]])
    with pytest.raises(ValueError, match="must belong to a world"):
        g.candidates(np.array([3]))
    with pytest.raises(ValueError, match="box worlds must be in"):
        BoxGroups.of(np.array([2]), 2)


def test_box_cast_matches_every_edge(scene_637f):
    """The lidar kernel (boxes beyond range skipped, only edges facing the agent cast) reads
    what casting every edge of every box reads, on the real scene's boxes at many steps."""
    from magail_sumo.sensors.base import Boxes
    from magail_sumo.sensors.raycast import cast, cast_boxes

    tr = scene_637f.tracks
    rng = np.random.default_rng(0)
    for t in range(0, tr.valid.shape[1], 5):
        rows = np.flatnonzero(tr.valid[:, t])
        b = Boxes(tr.x[rows, t], tr.y[rows, t], tr.heading[rows, t].astype(np.float64),
                  tr.length[rows, t].astype(np.float64), tr.width[rows, t].astype(np.float64))
        starts, ends, owner = b.edges()
        index = np.arange(len(b))
        origins = np.stack([b.x, b.y], axis=1)
        angles = rng.uniform(-np.pi, np.pi, (len(b), 1)) + np.linspace(0, 2 * np.pi, 80,
                                                                       endpoint=False)
        want = cast(origins, angles, 30.0, starts, ends, owner, index)
        got = cast_boxes(origins, angles, 30.0, starts, ends, index,
                         BoxGroups.single(len(b)))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
        assert (got < 30.0).any()
