"""SumoCityEnv on a real city (InTAS Ingolstadt cut-out) and the SUMO network as a road map."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from conftest import ROOT
from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv
from magail_sumo.errors import MagailSumoError
from magail_sumo.sim.sumo_map import network_map, offset_polyline

CITY = ROOT / "data" / "sumo" / "ingolstadt21"
CFG = CITY / "ingolstadt21.sumocfg"


def test_network_map_lanes_and_borders():
    import sumolib

    m = network_map(CITY / "ingolstadt21.net.xml")
    net = sumolib.net.readNet(str(CITY / "ingolstadt21.net.xml"), withInternal=True)
    n_lanes = sum(len(e.getLanes()) for e in net.getEdges(withInternal=True))
    assert len(m.roadmap.lanes) == len(m.lane_ids) == n_lanes
    lane = net.getLane(m.lane_ids[100])
    np.testing.assert_allclose(m.roadmap.lanes[100].polyline[:, :2], np.asarray(lane.getShape()))
    # a straight segment's border lies half a lane width to the side
    left = offset_polyline(np.array([[0.0, 0.0], [10.0, 0.0]]), 1.6)
    np.testing.assert_allclose(left, [[0.0, 1.6], [10.0, 1.6]])
    assert len(m.roadmap.road_edges) > 1000 and len(m.roadmap.road_lines) > 500


@pytest.mark.sumo
def test_city_episode_with_hundreds_of_agents():
    env = SumoCityEnv(CFG, CityEnvConfig(warmup_s=600, max_steps=30))
    obs, _ = env.reset(seed=0)
    assert len(env.agents) > 200  # every vehicle present after the warm-up is an agent
    reasons: dict[str, int] = {}
    nan_seen = 0
    first = env.agents[0]
    for _ in range(30):
        if not env.agents:
            break
        acts = {a: np.zeros(2, np.float32) for a in env.agents}
        acts[first] = np.array([np.nan, 0.0], np.float32)
        obs, rew, term, trunc, info = env.step(acts)
        for a, i in info.items():
            if i["reason"]:
                reasons[i["reason"]] = reasons.get(i["reason"], 0) + 1
        if first in info:
            nan_seen = info[first]["nan_actions"]
        for o in obs.values():
            assert np.isfinite(o).all()
    env.close()
    assert nan_seen >= 1
    assert sum(reasons.values()) > 200 and reasons.get("end_of_episode", 0) > 0
    # driving straight on with no steering makes agents leave the lanes or hit others
    assert reasons.get("off_road", 0) + reasons.get("collision", 0) > 0


@pytest.mark.sumo
def test_control_fraction_is_seeded():
    env = SumoCityEnv(CFG, CityEnvConfig(warmup_s=600, max_steps=5, control_fraction=0.25))
    env.reset(seed=1)
    a = set(env.agents)
    env.reset(seed=1)
    b = set(env.agents)
    env.reset(seed=2)
    c = set(env.agents)
    env.close()
    assert a == b and a != c and 0.1 < len(a) / 377 < 0.4


@pytest.mark.sumo
def test_parallel_api():
    env = SumoCityEnv(CFG, CityEnvConfig(warmup_s=600, max_steps=10, control_fraction=0.05))
    parallel_api_test(env, num_cycles=10)
    env.close()


def test_bad_scenario_files(tmp_path):
    with pytest.raises(MagailSumoError, match="nope.sumocfg: SUMO config file not found"):
        SumoCityEnv(tmp_path / "nope.sumocfg")
    bad = tmp_path / "bad.sumocfg"
    bad.write_text("<configuration><input><net-file value='missing.net.xml'/></input></configuration>")
    with pytest.raises(MagailSumoError, match="bad.sumocfg: net-file missing.net.xml: not found"):
        SumoCityEnv(bad)


@pytest.mark.sumo
def test_agent_cap_refills_from_waiting_vehicles():
    env = SumoCityEnv(CFG, CityEnvConfig(warmup_s=300, max_steps=40, max_agents=25))
    env.reset(seed=3)
    assert len(env.agents) == 25  # more vehicles than places: the first 25 are agents
    ended, counts = 0, []
    for _ in range(40):
        if not env.agents:
            break
        # full brake and steer hard: agents leave the lanes quickly
        obs, _, term, trunc, info = env.step({a: np.array([-1.0, 1.0], np.float32)
                                              for a in env.agents})
        ended += sum(bool(term[a] or trunc[a]) for a in term)
        counts.append(len(env.agents))
        st = env.agent_states()
        assert st.names == env.agents and st.state.x.shape == (len(env.agents),)
        assert len(env.agents) <= 25
    env.close()
    # agents ended, yet the city kept (nearly) 25: waiting vehicles joined mid-trip
    assert ended > 25 and max(counts[:-1]) == 25
