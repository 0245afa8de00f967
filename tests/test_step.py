"""The shared fleet state and step stages of both envs, and their one info contract."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR
from magail_sumo.env.fleet import Fleet, resized
from magail_sumo.env.step import END_OF_EPISODE, NO_ONE, FleetEnv
from magail_sumo.sim import dynamics

INFO_TYPES = {"step": int, "events": dict, "reason": (str, type(None)), "collided_with": str,
              "nan_actions": int, "clipped_actions": int, "state": tuple}


def test_fleet_roster_add_grow_and_queries():
    f = Fleet.roster(["7", "9"], np.array([4.0, 5.0]), np.array([2.0, 2.1]),
                     np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([0.1, 0.2]))
    assert len(f) == 2 and f.index == {"7": 0, "9": 1} and f.capacity == 2
    assert not f.active.any() and f.live().size == 0
    f.join(np.array([1]), dynamics.VehicleState(np.array([10.0]), np.array([20.0]),
                                                np.array([0.5]), np.array([3.0])))
    st = f.state(np.array([1]))
    assert f.live().tolist() == [1] and (st.x[0], st.y[0], st.yaw[0], st.speed[0]) == (10.0, 20.0, 0.5, 3.0)
    assert f.position(np.array([1])).tolist() == [[10.0, 20.0]]
    k = f.add("new", 1.0, 2.0, 0.0, 4.0, 4.5, 1.8)  # grows by doubling, rows kept
    assert k == 2 and f.capacity == 4 and f.names == ["7", "9", "new"] and f.index["new"] == 2
    assert f.length[:3].tolist() == [4.0, 5.0, 4.5] and f.dest[:2].tolist() == [[1, 2], [3, 4]]
    assert f.prev_action.shape == (4, dynamics.ACTION_SIZE) and f.nan_actions.dtype == np.int64
    assert not f.active[2] and not f.joined[3]
    f.active[1] = False
    assert f.left().tolist() == [False, True, False, False]
    assert resized(np.arange(3), 5).tolist() == [0, 1, 2, 0, 0]


def test_fleet_drive_is_the_bicycle_step_and_counts_fixes():
    f = Fleet.empty(3)
    for i in range(3):
        f.add(str(i), float(i), 0.0, 0.1 * i, 5.0, 4.8, 2.0)
    k = np.array([0, 2])
    f.join(k)
    act = np.array([[0.5, -0.2], [-1.0, 1.0]])
    lim = dynamics.BicycleLimits()
    want = dynamics.step(f.state(k), *dynamics.denormalise(act, lim, "steer_throttle"),
                         0.6 * f.length[k], 0.1, lim)
    f.drive(k, act, lim, "steer_throttle", 0.1)
    np.testing.assert_array_equal(f.x[k], want.x)
    np.testing.assert_array_equal(f.speed[k], want.speed)
    assert f.prev_action[k].tolist() == act.tolist() and f.x[1] == 1.0  # row 1 not moved
    f.count_fixes(k, np.array([True, False]), np.array([True, True]))
    assert f.nan_actions.tolist() == [1, 0, 0] and f.clipped_actions.tolist() == [1, 0, 1]
    st = f.agent_states(k, k + 100)
    assert st.names == ["0", "2"] and st.rows.tolist() == [100, 102]
    np.testing.assert_array_equal(st.wheelbase, dynamics.WHEELBASE_RATIO * f.length[k])


def test_checked_actions_one_stack_and_agent_by_agent_agree():
    """The usual step (every agent one (2,) array) takes one stack; any other dict is read
    agent by agent; both give the same clean actions and findings."""
    from magail_sumo.env.actions import _each_action, _every_action, checked_actions

    names = ["a", "b", "c"]
    usual = {"a": np.array([0.5, -2.0], np.float32), "b": np.array([np.nan, 0.1]),
             "c": np.array([1, 0]), "gone": np.zeros(2)}
    assert _every_action(usual, names) is not None
    clean, nonfinite, outside, missing, unknown = checked_actions(usual, names)
    raw, miss, present = _each_action(usual, names)
    assert np.array_equal(raw, _every_action(usual, names), equal_nan=True)
    assert present == 3 and not miss.any() and unknown == 1
    assert clean.tolist() == [[0.5, -1.0], [0.0, 0.1], [1.0, 0.0]]
    assert nonfinite.tolist() == [False, True, False] and outside.tolist() == [True, False, False]
    for odd in ({"a": [0.5, -2.0], "b": np.array([np.nan, 0.1]), "c": np.array([[1, 0]])},
                {"a": np.array([0.5, -2.0]), "b": None, "c": np.array([1.0, 0.0])},
                {"a": np.array([0.5, -2.0]), "c": np.array([1.0, 0.0])}):
        assert _every_action(odd, names) is None  # a list, a (1, 2) array, None, absent
        clean, nonfinite, outside, missing, unknown = checked_actions(odd, names)
        assert clean[0].tolist() == [0.5, -1.0] and clean[2].tolist() == [1.0, 0.0]
        assert nonfinite[1] and not nonfinite[[0, 2]].any() and unknown == 0
        assert missing.tolist() == [False, "b" not in odd or odd["b"] is None, False]
    with pytest.raises(ValueError, match="action of agent b: expected 2 numbers"):
        checked_actions({"a": np.zeros(2), "b": np.zeros(3), "c": np.zeros(2)}, names)


def test_both_envs_share_the_step():
    from magail_sumo.env import SumoCityEnv, SumoDrivingEnv

    for cls in (SumoDrivingEnv, SumoCityEnv):
        assert issubclass(cls, FleetEnv)
        for stage in ("_clean_actions", "_dynamics", "_events", "_outcomes", "_leave", "_infos_of",
                      "agent_states"):
            assert getattr(cls, stage) is getattr(FleetEnv, stage), (cls.__name__, stage)


def _check_infos(infos: dict, terms: dict, truncs: dict, names: set[str]) -> int:
    """Assert the info contract; the number of collisions seen."""
    hits = 0
    for a, i in infos.items():
        assert set(i) == set(INFO_TYPES), a
        for key, typ in INFO_TYPES.items():
            assert isinstance(i[key], typ), (a, key, i[key])
        assert len(i["state"]) == 4 and all(isinstance(v, float) for v in i["state"])
        hit = bool(i["events"].get("collision", False))
        assert hit == (i["collided_with"] != NO_ONE), (a, i)
        if hit:
            hits += 1
            assert i["collided_with"] != a and i["collided_with"] in names, i["collided_with"]
        if i["reason"] is not None:
            assert terms[a] or truncs[a]
    return hits


def _roll(env, road_users) -> tuple[int, set]:
    """An episode of seeded random actions checking every step's infos (``road_users()``: the
    names a collision may report); (collisions, reasons seen)."""
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    hits, reasons = 0, set()
    while env.agents:
        _, _, terms, truncs, infos = env.step({a: rng.uniform(-1, 1, 2) for a in env.agents})
        hits += _check_infos(infos, terms, truncs, road_users())
        reasons |= {i["reason"] for i in infos.values()}
    env.close()
    return hits, reasons


@pytest.mark.sumo
def test_driving_env_info_contract(bundled_networks):
    from converters import load_scene
    from magail_sumo.env import EnvConfig, SumoDrivingEnv

    scene = load_scene(WOMD_DIR / "637f20cafde22ff8.tfrecord")
    env = SumoDrivingEnv(scene, bundled_networks.bundle(scene.scenario_id),
                         EnvConfig(controlled="all", max_steps=30))
    names = {str(int(i)) for i in scene.tracks.id}
    hits, reasons = _roll(env, lambda: names)
    assert hits > 0 and END_OF_EPISODE in reasons and env.t == 30


@pytest.mark.sumo
def test_city_env_info_contract():
    from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv

    env = SumoCityEnv(ROOT / "data/sumo/ingolstadt21/ingolstadt21.sumocfg",
                      CityEnvConfig(warmup_s=300, max_steps=15, max_agents=60))
    hits, reasons = _roll(env, lambda: set(env._sumo.ids) | set(env.fleet.names))
    assert hits > 0 and END_OF_EPISODE in reasons
