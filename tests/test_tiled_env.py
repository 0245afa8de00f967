"""Several recorded scenes as one fleet (scene tiling, the tiled env, the tiled pool worker):
each scene's agents observe, act and end exactly as in the scene's own env, on every real
WOMD and ScenarioNet scene in data/ at once, in two training configs."""

from __future__ import annotations

import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from conftest import roll_random
from converters import load_scene
from converters.scene_files import RecordRef
from magail_sumo.env import EnvConfig
from magail_sumo.env.driving_env import SumoDrivingEnv
from magail_sumo.env.guard import GuardConfig
from magail_sumo.env.scene_pool import PoolCursor, max_concurrent_agents
from magail_sumo.env.tile_pool import TileCursor
from magail_sumo.env.tiled import TiledScenesEnv
from magail_sumo.env.vec_env import pool_vec_env
from magail_sumo.scene import validate_scene
from magail_sumo.scene.tiling import tile_scenes
from magail_sumo.sensors.config import ObservationConfig

ROOT = Path(__file__).resolve().parents[1]
SCENES = sorted((ROOT / "data" / "womd").glob("*.tfrecord")) + \
    sorted((ROOT / "data" / "scenarionet").glob("*.pkl"))

CONFIGS = {
    # the womd14 recipe's env: collision and off-road end an agent, lane off-road rule
    "recipe": EnvConfig(max_steps=80, sumo_mirror=False, terminate_on=("collision", "off_road")),
    # every event ends an agent; route-relative control, the gap guard, route command and
    # look-ahead, the leader, the road-edge rule (per tile; the nuScenes tile has no edges)
    "training": EnvConfig(max_steps=80, sumo_mirror=False, action_layout="accel_offset",
                          off_road_rule="road_edge", guard=GuardConfig(kind="gap"),
                          observation=ObservationConfig(command=True, route_points=(10.0, 30.0),
                                                        leader=True)),
}


def action(key: tuple[int, str], t: int) -> np.ndarray:
    """A fixed action of agent ``key`` (scene, track id) at step ``t``: spread over the whole
    box, braking hard one step in five (agents collide, leave the road, stop)."""
    h = zlib.crc32(f"{key}/{t}".encode())
    a = np.array([(h % 2000) / 1000.0 - 1.0, ((h >> 11) % 2000) / 1000.0 * 0.3 - 0.3],
                 np.float32)
    if (h >> 22) % 10 < 2:
        a[0] = -1.0
    return a


def play(env, key_of, options=None, shift=lambda key: 0) -> dict:
    """(agent key, its scene's log step, "obs" | "out") -> what the env gave, over one
    episode (``shift(key)``: how far the env's clock runs ahead of that scene's log)."""
    rec = {}
    obs, _ = env.reset(seed=1, options=options)
    step = lambda a: env.t - shift(key_of(a))  # noqa: E731
    for a, o in obs.items():
        rec[(key_of(a), step(a), "obs")] = np.array(o)
    while env.agents:
        obs, rew, term, trunc, info = env.step({a: action(key_of(a), step(a))
                                                for a in env.agents})
        for a, o in obs.items():
            rec[(key_of(a), step(a), "obs")] = np.array(o)
        for a in rew:
            i = info[a]
            rec[(key_of(a), step(a), "out")] = (rew[a], term[a], trunc[a], i["reason"],
                                                i["collided_with"],
                                                tuple(sorted(i["events"].items())), i["state"])
    return rec


@pytest.fixture(scope="module")
def real(bundled_networks):
    scenes = [load_scene(f) for f in SCENES]
    return scenes, [bundled_networks.bundle(f.stem) for f in SCENES]


def test_tiled_scene_is_a_valid_scene_with_every_scene_in_its_own_tile(real):
    scenes, _ = real
    tiled, tiling = tile_scenes(scenes, gap=2000.0)
    validate_scene(tiled)  # ids unique, references resolve, arrays consistent
    assert tiling.scenario_ids == tuple(s.scenario_id for s in scenes)
    assert tiled.num_steps == max(s.num_steps for s in scenes)
    boxes = []
    for k, s in enumerate(scenes):
        rows = np.arange(tiling.row_start[k], tiling.row_start[k + 1])
        tr, tt = s.tracks, tiled.tracks
        dx, dy = tiling.offsets[k]
        assert dx == int(dx) and dy == int(dy)  # whole metres
        assert (tiling.scene_of_rows(rows) == k).all()
        assert [tiling.scene_of_id(i) for i in tt.id[rows]] == [(k, int(i)) for i in tr.id]
        v = tr.valid
        np.testing.assert_array_equal(tt.valid[rows, :s.num_steps], v)
        assert not tt.valid[rows, s.num_steps:].any()
        np.testing.assert_array_equal(tt.x[rows, :s.num_steps][v], tr.x[v] + dx)  # exact
        np.testing.assert_array_equal(tt.y[rows, :s.num_steps][v], tr.y[v] + dy)
        np.testing.assert_array_equal(tt.heading[rows, :s.num_steps], tr.heading)
        xs = np.concatenate([tr.x[v] + dx] + [l.polyline[:, 0] + dx for l in s.roadmap.lanes])
        boxes.append((xs.min(), xs.max()))
        assert len(tiled.signals.lane[np.isin(tiled.signals.lane,
                                              [(k + 1) * tiling.feature_stride + i
                                               for i in s.signals.lane])]) == len(s.signals)
    for (_, hi), (lo, _) in zip(boxes, boxes[1:]):
        assert lo - hi >= 2000.0  # tiles apart by the gap, in order along x
    with pytest.raises(ValueError, match="given twice"):
        tile_scenes([scenes[0], scenes[0]])


@pytest.mark.sumo
@pytest.mark.parametrize("windows", ["fixed", "random"])
@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_each_scene_plays_in_the_tiled_env_as_in_its_own(real, config, windows):
    """Fixed windows: every scene from step 0. Random windows: each scene from a start of its
    own (the tiles delayed in time to start together)."""
    scenes, bundles = real
    cfg = CONFIGS[config]
    if windows == "random":
        cfg = replace(cfg, start_window="random")
    env = TiledScenesEnv(scenes, bundles, cfg)
    tiling = env.tiling
    opts = env.window_options(np.random.default_rng(5)) if windows == "random" else None
    starts = opts["start_steps"] if opts else [0] * len(scenes)
    assert windows == "fixed" or len(set(starts)) > 5
    alone: dict = {}
    for k, (s, b) in enumerate(zip(scenes, bundles)):
        alone.update(play(SumoDrivingEnv(s, b, cfg), lambda a, k=k: (k, a),
                          {"start_step": int(starts[k])}))

    def key(a: str) -> tuple[int, str]:
        k, tid = tiling.scene_of_id(int(a))
        return k, str(tid)
    tiled = play(env, key, opts, lambda key: int(env.shift[key[0]]))
    assert (env.shift == max(starts) - np.array(starts)).all()
    assert sorted(tiled) == sorted(alone)  # the same agents at the same steps
    assert {k[0][0] for k in tiled} == set(range(len(scenes)))
    exact, worst, outs = 0, 0.0, 0
    for k, a in alone.items():
        b = tiled[k]
        if k[2] == "obs":
            exact += np.array_equal(a, b)
            worst = max(worst, float(np.abs(a.astype(np.float64) - b).max()))
            continue
        hit = b[4]
        if hit and int(hit) >= tiling.track_stride:  # the road user's own id in its scene
            hit = str(tiling.scene_of_id(int(hit))[1])
        assert a[:4] == b[:4] and a[4] == hit and a[5] == b[5], k  # rewards, ends, events
        offset = tiling.offsets[k[0][0]]
        np.testing.assert_allclose(np.array(b[6][:2]) - offset, a[6][:2], atol=1e-6)
        outs += 1
    n = sum(k[2] == "obs" for k in alone)
    assert outs > 1000 and n > 10_000
    # a translated position rounds differently in its last bits: observations agree to float32
    # rounding, most of them bit for bit
    assert worst < 1e-5, worst
    assert exact / n > 0.98, exact / n
    ends = {v[3] for k, v in tiled.items() if k[2] == "out" and (v[1] or v[2])}
    assert {"collision", "off_road"} <= ends  # the episode exercised the events


def test_tiled_env_refuses_what_it_cannot_run(real):
    scenes, bundles = real
    two = scenes[:2], bundles[:2]
    for cfg, words in [(EnvConfig(), "sumo_mirror"),
                       (EnvConfig(sumo_mirror=False, controlled=4), "controlled"),
                       (EnvConfig(sumo_mirror=False, controlled="sdc"), "controlled"),
                       (EnvConfig(sumo_mirror=False,
                                  observation=ObservationConfig(layout="scene_frame")),
                        "ego frame")]:
        with pytest.raises(ValueError, match=words):
            TiledScenesEnv(*two, cfg)
    with pytest.raises(ValueError, match="one bundle per scene"):
        TiledScenesEnv(scenes[:2], bundles[:1], EnvConfig(sumo_mirror=False))
    env = TiledScenesEnv(*two, EnvConfig(sumo_mirror=False))
    per = env.split({a: a for a in env.possible_agents})
    for k, (s, b) in enumerate(zip(*two)):  # each scene's agents under their own ids
        assert sorted(per[k], key=int) == sorted(SumoDrivingEnv(s, b, env.config).possible_agents,
                                                 key=int)
        assert (env.scene_of(list(per[k].values())) == k).all()
    assert env.merge(per) == {a: a for a in env.possible_agents}


def test_tile_cursor_groups_are_seeded_and_cover_each_pass(tmp_path):
    refs = [RecordRef(str(f)) for f in SCENES[:7]]
    pool = PoolCursor(refs, tmp_path, seed=3, make_env=None, config=EnvConfig(sumo_mirror=False))
    cur = TileCursor(pool, 3, EnvConfig(sumo_mirror=False))
    for epoch in range(3):
        groups = cur.groups(epoch)
        assert [len(g) for g in groups] == [3, 3, 1]
        assert sorted(k for g in groups for k in g) == list(range(7))
        assert all(list(g) == sorted(g) for g in groups)
    assert cur.groups(0) == TileCursor(PoolCursor(refs, tmp_path, 3, None, EnvConfig()), 3,
                                       EnvConfig()).groups(0)
    assert cur.groups(0) != cur.groups(1)


@pytest.mark.sumo
def test_pool_workers_with_tiled_envs_play_every_scene_and_resume_exactly(bundled_networks):
    """Two workers, each stepping its three scenes as one tiled env: every scene plays, the
    slots are the tiles' most concurrent agents, and a rollout replays exactly."""
    files = SCENES[:6]
    refs = [RecordRef(str(f)) for f in files]
    nets = bundled_networks(*(f.stem for f in files))
    cfg = EnvConfig(start_window="random", max_steps=30, sumo_mirror=False,
                    terminate_on=("collision", "off_road"))
    venv = pool_vec_env(refs, nets, 2, cfg, seed=5, scenes_per_env=3)
    try:
        solo = [pool_vec_env(refs[w::2], nets, 1, cfg, seed=5, scenes_per_env=3)
                for w in range(2)]
        try:
            assert venv.slots == [v.slots[0] for v in solo]
        finally:
            for v in solo:
                v.close()
        scenes = set()
        obs = roll_random(venv, 50, hook=lambda t, v: scenes.update(v.worker_scene))
        again = roll_random(venv, 50)
    finally:
        venv.close()
    assert all(s.startswith("tiles-") for s in scenes)
    assert {sid for s in scenes for sid in s[len("tiles-"):].split("+")} == \
        {f.stem for f in files}
    for a, b in zip(obs, again):
        np.testing.assert_array_equal(a, b)


@pytest.mark.sumo
def test_slots_hold_every_agent_when_agents_drive_past_their_logs_end(real):
    """With ``end_of_life: false`` an agent lives to its window's end, not its log's: the
    slot bound (each tile's most concurrent agents, summed) still holds every live agent."""
    scenes, bundles = real
    cfg = EnvConfig(start_window="random", max_steps=80, sumo_mirror=False, end_of_life=False,
                    terminate_on=("collision", "off_road"))
    def most_alive(env, starts) -> int:
        most = 0
        for episode, opts in enumerate(starts):
            env.reset(seed=episode, options=opts)
            while env.agents:
                most = max(most, len(env.agents))
                env.step({a: np.array([0.2, 0.0], np.float32) for a in env.agents})
        return most

    k = next(i for i, f in enumerate(SCENES) if f.stem == "7b24d74b506c94ce")
    alone = SumoDrivingEnv(scenes[k], bundles[k], cfg)
    by_log = max_concurrent_agents(SumoDrivingEnv(scenes[k], bundles[k],
                                                  replace(cfg, end_of_life=True)))
    most = most_alive(alone, [{"start_step": s} for s in (94, 106, 118)])
    assert by_log < most <= max_concurrent_agents(alone)  # more than the log alone keeps
    env = TiledScenesEnv(scenes[:6], bundles[:6], cfg)
    rng = np.random.default_rng(0)
    most = most_alive(env, [env.window_options(rng) for _ in range(3)])
    assert 0 < most <= env.max_concurrent_agents()
