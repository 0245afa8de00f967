"""The drivers' own desired speeds (``observation.speed_factor``): in a real SUMO city each
agent reads the factor SUMO drew for its vehicle, the IDM rule drives the limit times it; in a
recorded scene it reads 1 (issue 32: with one desired speed for all, 68 % of the Wildau agents'
time was at 12-14 m/s)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from conftest import ROOT, SCENARIONET_DIR
from magail_sumo.env.fleet import Fleet
from magail_sumo.models.idm import IdmRule
from magail_sumo.sensors.observation import ObservationConfig, observation_names

COLOGNE8 = ROOT / "data" / "sumo" / "cologne8" / "cologne8.sumocfg"
OBS = ObservationConfig(path_leader=True, light_gap=True, route_points=(5.0, 10.0, 20.0),
                        speed_limit=True, speed_factor=True)


@pytest.mark.sumo
def test_city_agents_read_the_factor_sumo_drew_for_them():
    """On cologne8 every agent's ``speed_factor`` is its SUMO vehicle's ``getSpeedFactor``
    (SUMO's default spread for cars: not all alike, within the distribution's cut), and the
    IDM rule's free-road acceleration of the same rows is lower for the slower drivers."""
    from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv
    from magail_sumo.env.config import EnvConfig

    cfg = CityEnvConfig.from_env(EnvConfig(action_layout="accel_offset", observation=OBS),
                                 max_agents=60, control_fraction=1.0, warmup_s=300,
                                 max_steps=50)
    env = SumoCityEnv(COLOGNE8, cfg)
    col = observation_names(OBS).index("speed_factor")
    try:
        obs, _ = env.reset(seed=0)
        for _ in range(20):
            obs, *_ = env.step({a: np.zeros(2, np.float32) for a in obs})
        assert len(obs) >= 20
        api = env._session.api
        got = np.array([obs[a][col] for a in sorted(obs)])
        want = np.array([api.vehicle.getSpeedFactor(a) for a in sorted(obs)])
    finally:
        env.close()
    assert np.allclose(got, want, atol=1e-6)
    assert got.std() > 0.02 and (got > 0.2).all() and (got < 2.0).all()
    rows = np.stack([obs[a] for a in sorted(obs)])
    rule = IdmRule(OBS)
    free = rows.copy()
    free[:, observation_names(OBS).index("path_leader_gap")] = OBS.leader_range
    one = free.copy()
    one[:, col] = 1.0
    slow = got < 1.0
    assert slow.any() and (~slow).any()
    a_own, a_one = rule.accel(free), rule.accel(one)
    assert (a_own[slow] <= a_one[slow] + 1e-9).all() and (a_own[~slow] >= a_one[~slow] - 1e-9).all()


def test_the_rule_drives_the_limit_times_the_factor():
    """Free road, no bend, no light: the rule's acceleration vanishes at limit × factor (the
    IDM's desired speed), for factors below and above 1."""
    names = observation_names(OBS)
    rule = IdmRule(OBS)
    rows = np.zeros((3, len(names)), np.float64)
    rows[:, names.index("path_leader_gap")] = OBS.leader_range
    rows[:, names.index("light_gap")] = 1e3
    for i, d in enumerate(OBS.route_points):
        rows[:, names.index(f"route_x_{d:g}")] = d
    rows[:, names.index("speed_limit")] = rows[:, names.index("speed_limit_ahead")] = 13.9
    factor = np.array([0.8, 1.0, 1.15])
    rows[:, names.index("speed_factor")] = factor
    rows[:, names.index("speed")] = 13.9 * factor
    assert np.allclose(rule.accel(rows), 0.0, atol=1e-9)
    rows[:, names.index("speed")] = 13.9
    a = rule.accel(rows)
    assert a[0] < 0 and abs(a[1]) < 1e-9 and a[2] > 0


@pytest.mark.sumo
def test_recorded_scene_reads_one(bundled_networks):
    """A recorded driver's wish is not observed: every agent of a real WOMD scene reads 1."""
    from converters import load_scene
    from magail_sumo.env import EnvConfig, SumoDrivingEnv

    sid = "49c341dce1f65cdb"
    scene = load_scene(SCENARIONET_DIR / f"{sid}.pkl")
    ob = replace(OBS, route_stop=True)
    cfg = EnvConfig(controlled="all", start_step=10, max_steps=3, action_layout="accel_offset",
                    observation=ob)
    env = SumoDrivingEnv(scene, bundled_networks.bundle(sid), cfg)
    try:
        obs, _ = env.reset(seed=0)
    finally:
        env.close()
    col = observation_names(ob).index("speed_factor")
    assert obs and all(o[col] == 1.0 for o in obs.values())


def test_a_grown_fleet_starts_its_new_rows_at_one():
    f = Fleet.empty(2)
    for i in range(5):
        f.add(f"v{i}", 0.0, 0.0, 0.0, 0.0, 4.5, 1.8)
    f.speed_factor[0] = 0.9
    f.grow(40)
    assert f.speed_factor[0] == 0.9 and (f.speed_factor[1:] == 1.0).all()
    assert (f.path[5:] == -1).all()


def test_checkpoint_brings_the_factor_to_evaluation(tmp_path):
    from conftest import tiny_checkpoint
    from magail_sumo import policies

    ckpt = tiny_checkpoint(tmp_path / "speed.pt", {"observation": {
        "speed_factor": True, "speed_limit": True, "path_leader": True}})
    policy = policies.make_policy(str(ckpt), 0)
    assert policy.observation.speed_factor and policy.observation.speed_limit
    assert policy.obs_dim == len(observation_names(policy.observation))
    assert observation_names(policy.observation)[-1] == "speed_factor"
