"""Scene pools: listing, sharding, seeded order, on-demand conversion, skipped scenes, exact
resume, and lost workers replaced with their episode replayed (real scenes, real SUMO)."""

from __future__ import annotations

import json
import os
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest

from conftest import WOMD_DIR, killed_worker_ends_the_env, roll_random
from converters.scene_files import RecordRef, list_records, read_record
from magail_sumo.env.config import EnvConfig
from magail_sumo.env.scene_pool import (PoolCursor, agent_bound, resolve_pool, shard_pool,
                                        write_skipped)
from magail_sumo.env.vec_env import pool_vec_env

ROOT = Path(__file__).resolve().parents[1]
SN = ROOT / "data" / "scenarionet"
SMALL = [WOMD_DIR / "850c48d8bbfa008f.tfrecord", SN / "250011f460de6135.pkl",
         SN / "53e9adfdac0eb822.pkl"]
#: their scenario ids (the file names' stems): bundled scenes, converted once per session
POOL = tuple(f.stem for f in SMALL)
CFG = EnvConfig(start_window="random", max_steps=15, controlled=6)


@pytest.fixture(scope="module")
def pool_dir(tmp_path_factory):
    """Three real scenes, one file that is not a scene, in one folder."""
    d = tmp_path_factory.mktemp("pool")
    for f in SMALL:
        shutil.copy(f, d / f.name)
    (d / "broken.pkl").write_bytes(b"\x80\x04not a pickle at all")
    return d


# ------------------------------------------------------------------ listing (no SUMO)
def test_resolve_pool_entries(pool_dir, tmp_path):
    skipped = []
    refs = resolve_pool([str(pool_dir), str(SN / "2a1e*.pkl"), str(tmp_path / "none*.pkl")],
                        skipped)
    names = [Path(r.path).name for r in refs]
    assert names == ["250011f460de6135.pkl", "53e9adfdac0eb822.pkl",
                     "850c48d8bbfa008f.tfrecord", "broken.pkl", "2a1e44d405a6833f.pkl"]
    assert [s.what for s in skipped] == [str(tmp_path / "none*.pkl")]
    assert "matches no file" in skipped[0].reason
    assert list_records(WOMD_DIR / "850c48d8bbfa008f.tfrecord") == [
        RecordRef(str(WOMD_DIR / "850c48d8bbfa008f.tfrecord"), 0)]
    assert read_record(refs[0]).scenario_id == "250011f460de6135"
    empty = tmp_path / "empty"
    empty.mkdir()
    skipped = []
    assert resolve_pool([str(empty)], skipped) == [] and "no scene file" in skipped[0].reason


def test_shards_and_seeded_order():
    refs = [RecordRef(f"s{i}.pkl") for i in range(7)]
    shards = shard_pool(refs, 3)
    assert [len(s) for s in shards] == [3, 2, 2] and shards[1] == (refs[1], refs[4])
    # more workers than records: replicas (each worker one record, w mod n); never empty
    assert shard_pool(refs[:2], 5) == [(refs[0],), (refs[1],), (refs[0],), (refs[1],),
                                       (refs[0],)]
    assert shard_pool(refs[:1], 1) == [(refs[0],)] and shard_pool([], 3) == []
    cur = PoolCursor(refs, "nets", seed=5, make_env=None, config=CFG)
    again = PoolCursor(refs, "nets", seed=5, make_env=None, config=CFG)
    orders = [cur.order(e) for e in range(4)]
    assert all(sorted(o.tolist()) == list(range(7)) for o in orders)  # a pass plays each once
    assert all(np.array_equal(a, again.order(e)) for e, a in enumerate(orders))
    assert not all(np.array_equal(orders[0], o) for o in orders[1:])  # passes differ
    other = PoolCursor(refs, "nets", seed=6, make_env=None, config=CFG)
    assert not np.array_equal(other.order(0), orders[0])


def test_skipped_file_is_not_repeated(tmp_path):
    from magail_sumo.env.scene_pool import PoolSkip

    f = tmp_path / "skipped_scenes.tsv"
    write_skipped(f, [PoolSkip("a.pkl", "bad")])
    write_skipped(f, [PoolSkip("a.pkl", "bad"), PoolSkip("b.pkl", "worse\nline")])
    assert f.read_text().splitlines() == ["scene\treason", "a.pkl\tbad", "b.pkl\tworse line"]


def test_large_shard_reads_only_its_first_scenes_at_start(tmp_path):
    """A worker sizes its slots from the first SCAN_RECORDS records of its order; the rest are
    read when played (a 100,000-file pool starts as fast as a 64-file one), and a scene that
    needs more slots than that is skipped then, with the reason."""
    from magail_sumo.env.scene_pool import SCAN_RECORDS

    real = sorted(SN.glob("*.pkl"))
    refs = [RecordRef(str(tmp_path / f"gone{i}.pkl")) for i in range(3 * SCAN_RECORDS)]
    refs[::16] = [RecordRef(str(f)) for f in real[:len(refs[::16])]]
    cur = PoolCursor(refs, tmp_path / "nets", seed=1, make_env=None,
                     config=EnvConfig(start_window="random", max_steps=15))
    slots = cur.scan()
    first = set(cur.order(0)[:SCAN_RECORDS].tolist())
    assert slots == cur.slots >= 1
    assert set(cur.failed) <= first  # nothing outside the first 64 was read
    assert len(cur.failed) == sum(not Path(refs[k].path).exists() for k in first)
    big = max(range(len(real)), key=lambda i: agent_bound(read_record(RecordRef(str(real[i]))),
                                                          cur.config))
    k = refs.index(RecordRef(str(real[big])))
    cur.slots = 1
    with pytest.raises(Exception, match=r"env start: up to \d+ agents alive at once, more "
                                        r"than the worker's 1 slots"):
        cur.env(k)


def test_bad_bundles_in_a_pool_folder_are_skipped_not_fatal(tmp_path):
    """A deeply nested or endless ``conversion.json`` (a FIFO, /dev/zero) skips its bundle in
    seconds; the pool goes on with the rest."""
    import time

    nets = tmp_path / "nets"
    for name in ("deep", "fifo", "zero", "good"):
        (nets / name).mkdir(parents=True)
    (nets / "deep" / "conversion.json").write_text("[" * 200_000 + "]" * 200_000)
    os.mkfifo(nets / "fifo" / "conversion.json")
    (nets / "zero" / "conversion.json").symlink_to("/dev/zero")
    (nets / "good" / "conversion.json").write_text(json.dumps(
        {"status": "ok", "source": {"file": str(SMALL[1]), "record": 0}}))
    skipped = []
    t0 = time.monotonic()
    refs = resolve_pool([str(nets)], skipped)
    assert time.monotonic() - t0 < 10
    assert refs == [RecordRef(str(SMALL[1]), 0)]
    why = {Path(s.what).name: s.reason for s in skipped}
    assert "JSON nested deeper than 64 levels" in why["deep"]
    assert "is a FIFO" in why["fifo"] and "is a character device" in why["zero"]


# ------------------------------------------------------------------ real SUMO
@pytest.mark.sumo
def test_agent_bound_covers_every_window(tmp_path):
    from magail_sumo.env.driving_env import SumoDrivingEnv
    from converters.sumo.scenario import ensure_bundle
    from magail_sumo.env.vec_env import max_concurrent_agents

    for f in SMALL + [SN / "2a1e44d405a6833f.pkl"]:
        scene = read_record(list_records(f)[0])
        bundle = ensure_bundle(scene, tmp_path / "nets", RecordRef(str(f)))
        assert json.loads((bundle / "conversion.json").read_text())["source"] == {
            "file": str(f), "record": 0}
        for cfg in (EnvConfig(start_window="random", max_steps=20), CFG,
                    EnvConfig(controlled="scored")):
            env = SumoDrivingEnv(scene, bundle, cfg)
            assert agent_bound(scene, cfg) >= max_concurrent_agents(env), (f, cfg.controlled)
    # the bundles folder is a pool too: each bundle names its scene
    assert {Path(r.path).name for r in resolve_pool([str(tmp_path / "nets")])} == \
        {f.name for f in SMALL} | {"2a1e44d405a6833f.pkl"}


@pytest.mark.sumo
def test_pool_plays_every_scene_skips_the_bad_one_and_resumes_exactly(pool_dir, tmp_path):
    refs = resolve_pool([str(pool_dir)])
    logs: list[str] = []
    venv = pool_vec_env(refs, tmp_path / "nets", 2, CFG, seed=4, log=logs.append)
    seen: set[str] = set()
    try:
        assert venv.slots == [6, 6]  # sized to the largest bound of each shard, capped at K
        assert len(venv.specs) == 2 and venv.num_envs == 12
        obs = roll_random(venv, 60, hook=lambda t, v: seen.update(v.worker_scene))
        state_at = None

        def grab(t, v):
            nonlocal state_at
            if t == 37:
                state_at = v.get_state()
        obs2 = roll_random(venv, 45, hook=grab)  # the same rollout again from a reset
    finally:
        venv.close()
    for a, b in zip(obs, obs2):
        np.testing.assert_array_equal(a, b)
    assert seen == {"850c48d8bbfa008f", "250011f460de6135", "53e9adfdac0eb822"}
    assert venv.skipped == [(str(pool_dir / "broken.pkl"), venv.skipped[0][1])]
    assert "record 0: unreadable pickle" in venv.skipped[0][1]
    assert any(line.startswith(f"scene skipped: {pool_dir / 'broken.pkl'}: ") for line in logs)
    # each scene converted once, on demand, into the pool's networks folder
    assert sorted(p.name for p in (tmp_path / "nets").iterdir() if not p.name.startswith(".")) \
        == sorted(["850c48d8bbfa008f", "250011f460de6135", "53e9adfdac0eb822"])
    # exact resume: a fresh env set to the state after 37 steps continues identically
    fresh = pool_vec_env(refs, tmp_path / "nets", 2, CFG, seed=4)
    try:
        got = [fresh.set_state(state_at)]
        rng = np.random.default_rng(0)
        acts = [rng.uniform(-1, 1, (fresh.num_envs, 2)).astype(np.float32) for _ in range(45)]
        got += [fresh.step(a)[0] for a in acts[37:]]
    finally:
        fresh.close()
    assert len(got) == len(obs2[37:]) == 9
    for a, b in zip(got, obs2[37:]):
        np.testing.assert_array_equal(a, b)


@pytest.mark.sumo
def test_kept_scene_envs_play_exactly_as_freshly_built_ones(pool_dir, bundled_networks):
    """A worker keeping its scenes' envs (the default cache) plays the same rollouts as one
    that rebuilds the env at every scene change (cache 1): a reused env carries nothing from
    its earlier episodes."""
    refs = [r for r in resolve_pool([str(pool_dir)]) if not r.path.endswith("broken.pkl")][:2]
    runs = []
    for cache in (1, 16):
        venv = pool_vec_env(refs, bundled_networks(*POOL), 1, CFG, seed=7, cache=cache)
        scenes: list[str] = []
        try:
            runs.append(roll_random(venv, 70, hook=lambda t, v: scenes.extend(v.worker_scene)))
        finally:
            venv.close()
        assert len(set(scenes)) == 2  # both scenes played, several episodes each
    for a, b in zip(*runs):
        np.testing.assert_array_equal(a, b)


@pytest.mark.sumo
def test_worker_with_only_bad_scenes_is_dropped_at_start(pool_dir, tmp_path, bundled_networks):
    refs = [RecordRef(str(pool_dir / "broken.pkl")), RecordRef(str(SMALL[0]))]
    venv = pool_vec_env(refs, bundled_networks(*POOL), 2, CFG, seed=0)
    try:
        assert venv.skipped[0][0] == str(pool_dir / "broken.pkl")
        # the 2 workers asked for both play the scene left (replicas with their own seeds)
        assert [s.refs for s in venv.specs] == [(refs[1],), (refs[1],)]
        venv.reset()
    finally:
        venv.close()
    with pytest.raises(Exception, match="no scene of the pool can be used"):
        pool_vec_env(refs[:1], tmp_path / "nets", 1, CFG)


@pytest.mark.sumo
@pytest.mark.parametrize("how", ["kill", "hang"])
def test_lost_worker_is_replaced_and_the_rollout_goes_on_unchanged(how, bundled_networks):
    refs = [RecordRef(str(f)) for f in SMALL]
    nets = bundled_networks(*POOL)
    base = pool_vec_env(refs, nets, 2, CFG, seed=9)
    try:
        want = roll_random(base, 40)
    finally:
        base.close()

    def fault(t, v):
        if t == 23:  # mid-episode, mid-rollout
            os.kill(v._handles[1].pid, signal.SIGKILL if how == "kill" else signal.SIGSTOP)
            v.timeout_s = 4.0

    logs: list[str] = []
    venv = pool_vec_env(refs, nets, 2, CFG, seed=9, max_restarts=2,
                        log=logs.append)
    try:
        pid = venv._handles[1].pid
        got = roll_random(venv, 40, hook=fault)
        assert venv.restarts == 1 and venv._handles[1].pid != pid
    finally:
        venv.close()
    for a, b in zip(want, got):
        np.testing.assert_array_equal(a, b)
    (line,) = [m for m in logs if m.startswith("worker 1 ")]
    assert ("died" if how == "kill" else "did not answer within 4 s") in line
    assert "replaced" in line and "replayed" in line
    # no replacement allowed: the env gives up with one line
    killed_worker_ends_the_env(pool_vec_env(refs, nets, 2, CFG, seed=9, max_restarts=0))


@pytest.mark.sumo
def test_train_on_a_pool_folder_lists_skipped_scenes_and_resumes(pool_dir, tmp_path,
                                                                  bundled_networks):
    import yaml

    from magail_sumo.config import from_dict
    from magail_sumo.env.scene_specs import scene_specs
    from magail_sumo.expert import record_expert
    from magail_sumo.training.config import TrainConfig, usable_cores
    from magail_sumo.training.trainer import train

    nets = bundled_networks(*POOL)  # the pool's scenes, converted
    record_expert(scene_specs([SMALL[0]], nets), tmp_path / "expert")
    raw = {"seed": 1, "expert_dir": str(tmp_path / "expert"), "updates": 2, "checkpoint_every": 1,
           "env": {"max_steps": 15, "start_window": "random", "controlled": 6},
           "scenes": {"files": [str(pool_dir)], "networks": str(nets)},
           "policy": {"actor_hidden": [16, 16], "critic_hidden": [16, 16]},
           "ppo": {"n_steps": 16, "batch_size": 32, "n_epochs": 1},
           "discriminator": {"kind": "mlp", "epochs": 1, "batch_size": 16}}
    logs: list[str] = []
    run = train(from_dict(TrainConfig, raw), tmp_path / "run", log=logs.append)
    want = min(4, usable_cores())
    # (a worker left with only the broken file is dropped at start: one fewer on > 3 cores)
    assert any(m.startswith("scene pool: 4 scene(s) over ") and " process worker(s)" in m
               for m in logs), logs
    assert yaml.safe_load((run / "config.yaml").read_text())["workers"]["count"] == want
    lines = (run / "skipped_scenes.tsv").read_text().splitlines()
    assert lines[0] == "scene\treason" and len(lines) == 2
    assert lines[1].startswith(f"{pool_dir / 'broken.pkl'}\trecord 0: unreadable pickle")
    raw["updates"] = 3  # count stays null: the run's resolved number is used
    train(from_dict(TrainConfig, raw), resume=run, log=logs.append)
    assert any(m.startswith("update 3/3") for m in logs)
    assert len((run / "skipped_scenes.tsv").read_text().splitlines()) == 2


@pytest.mark.sumo
def test_city_scenario_trains_beside_a_recorded_scene(tmp_path, bundled_networks):
    from magail_sumo.config import ConfigError, from_dict
    from magail_sumo.env.scene_specs import scene_specs
    from magail_sumo.expert import ExpertDataset, record_expert
    from magail_sumo.sensors.observation import observation_names
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.preflight import check_train_config
    from magail_sumo.training.trainer import GailRun

    city = ROOT / "data" / "sumo" / "ingolstadt21"
    nets = bundled_networks(SMALL[0].stem)
    record_expert(scene_specs([SMALL[0]], nets), tmp_path / "expert")
    raw = {"seed": 0, "expert_dir": str(tmp_path / "expert"),
           "env": {"max_steps": 15, "start_window": "random"},
           "scenes": {"files": [str(city), str(SMALL[0])], "networks": str(nets)},
           "workers": {"count": 2},
           "city": {"max_agents": 40, "warmup_s": 300, "max_steps": 30},
           "policy": {"actor_hidden": [16, 16], "critic_hidden": [16, 16]},
           "ppo": {"n_steps": 16, "batch_size": 86, "n_epochs": 1},
           "discriminator": {"kind": "decomposed", "epochs": 1, "batch_size": 16}}
    with pytest.raises(ConfigError, match=r"discriminator\.kind: 'transformer' judges all "
                                          r"vehicles of a worker step as one set"):
        check_train_config(from_dict(TrainConfig, {**raw, "discriminator": {}}))
    cfg = from_dict(TrainConfig, raw)
    check_train_config(cfg)
    expert = ExpertDataset(cfg.expert_dir, observation_names(cfg.env.observation))
    run = GailRun(cfg, expert)
    try:
        venv = run.venv
        assert venv.slots[0] == 40  # the city worker: max_agents slots
        run.run_update()
        assert venv.worker_scene[0] == "ingolstadt21"
        city_steps = venv.agent_steps
        assert city_steps > 16 * 30  # the city kept tens of agents driving every step
        run.run_update()
        assert run.update == 2
    finally:
        run.close()


def test_resume_keeps_the_runs_worker_count():
    from magail_sumo.config import from_dict, to_dict
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.trainer import resume_worker_count

    now = from_dict(TrainConfig, {"scenes": {"files": [str(f) for f in SMALL]}})
    # a run that resolved 2 workers resumes with 2 when the config leaves the count null
    saved = to_dict(from_dict(TrainConfig, {"workers": {"count": 2}}))
    cfg, cmp = resume_worker_count(now, {"config": saved, "env_state": [0, 0]})
    assert cfg.workers.count == 2 and cmp["workers"]["count"] == 2
    # a checkpoint from before worker pools: one worker per scene of its env state
    old = {k: v for k, v in to_dict(now).items() if k != "workers"}
    cfg, cmp = resume_worker_count(now, {"config": old, "env_state": [0, 0, 0]})
    assert cfg.workers.count == 3 and cmp["workers"] == {"count": 3}
    # an explicit count in the config is kept (a differing one is refused by the config check)
    pinned = from_dict(TrainConfig, {"workers": {"count": 3}})
    cfg, cmp = resume_worker_count(pinned, {"config": old, "env_state": [0, 0, 0]})
    assert cfg.workers.count == 3 and cmp["workers"]["count"] == 3
