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


# ------------------------------------------------------------------ any scenario SUMO runs
SHARED_SUMO = ROOT.parent / "shared" / "data" / "sumo"
#: every city scenario here, and in ../shared when present: each loads unedited
SCENARIOS = sorted((ROOT / "data" / "sumo").glob("*/*.sumocfg")) + (
    sorted(SHARED_SUMO.rglob("*.sumocfg")) if SHARED_SUMO.is_dir() else [])


@pytest.mark.sumo
@pytest.mark.parametrize("cfg", SCENARIOS, ids=lambda p: str(p.relative_to(p.parents[2])))
def test_every_city_scenario_loads_unedited_or_names_what_is_missing(cfg):
    """Each runs a few steps with its own layout, begin time, gzip, additional files, public
    transport and pedestrians, or fails in one line naming the configuration and the file SUMO
    would also miss (some DLR configurations name route files their tools generate)."""
    import re
    from magail_sumo.sim.sumo_config import read_config

    missing = None
    try:
        read_config(cfg)
    except MagailSumoError as exc:
        missing = str(exc)
    if missing is not None:
        assert "\n" not in missing and str(cfg) in missing
        assert re.search(r": (route-files|additional-files|net-file) \S.*: not found$", missing)
        name = missing.split(": ")[-2].split(" ", 1)[1]
        assert not (cfg.parent / name).exists()  # SUMO would miss it too
        return
    env = SumoCityEnv(cfg, CityEnvConfig(warmup_s=0, max_steps=10, max_agents=8))
    try:
        env.reset(seed=0)
        for _ in range(10):
            env.step({a: np.zeros(2, np.float32) for a in env.agents})
        assert env.sumo_time is not None
    finally:
        env.close()


@pytest.mark.sumo
def test_any_config_name_a_folder_and_a_config_where_a_scene_is_expected(tmp_path):
    """``run.sumo.cfg`` in a folder, a flat layout with a gzipped route file: the city env,
    evaluate --city and a training pool take it; inspect names it a city."""
    import gzip
    import shutil

    from converters.scene_files import detect_format
    from magail_sumo.env.scene_pool import is_city, resolve_pool
    from magail_sumo.errors import SceneFormatError
    from magail_sumo.evaluation.city import city_config

    city = tmp_path / "monaco"
    city.mkdir()
    shutil.copy(CITY / "ingolstadt21.net.xml", city / "net.net.xml")
    (city / "demand.rou.xml.gz").write_bytes(
        gzip.compress((CITY / "ingolstadt21.rou.xml").read_bytes()))
    cfg = city / "run.sumo.cfg"
    cfg.write_text('<configuration><net-file value="net.net.xml"/>'
                   '<route-files value="demand.rou.xml.gz"/><begin value="25200"/>'
                   "</configuration>")
    assert city_config(city) == cfg and city_config(cfg) == cfg
    refs = resolve_pool([str(city)])
    assert [r.path for r in refs] == [str(cfg)] and is_city(refs[0])
    env = SumoCityEnv(cfg, CityEnvConfig(warmup_s=0, max_steps=5))
    assert env.scenario_id == "monaco" and len(env.possible_agents) > 100
    env.reset(seed=0)
    env.close()
    for where in (cfg, city):
        with pytest.raises(SceneFormatError, match="a SUMO scenario \\(city\\), not a recorded "
                                                   "scene: evaluate it with `magail-sumo "
                                                   "evaluate --city`"):
            detect_format(where)


@pytest.mark.sumo
def test_only_the_chosen_classes_without_stops_become_agents(tmp_path):
    """Buses (and any vehicle with stops) stay SUMO-driven by default; choosing the class
    makes buses without stops agents."""
    import re

    text = (CITY / "ingolstadt21.rou.xml").read_text()
    buses = set(re.findall(r'<(?:vehicle|trip) id="([^"]+)" type="bus"', text))
    assert buses, "ingolstadt21 has buses"
    env = SumoCityEnv(CFG, CityEnvConfig(warmup_s=0, max_steps=600))
    seen: set[str] = set()
    env.reset(seed=0)
    for _ in range(600):
        seen.update(env.agents)
        env.step({a: np.zeros(2, np.float32) for a in env.agents})
    env.close()
    assert seen and not (seen & buses)
    env = SumoCityEnv(CFG, CityEnvConfig(warmup_s=0, max_steps=600,
                                         agent_classes=("passenger", "bus")))
    both: set[str] = set()
    env.reset(seed=0)
    for _ in range(600):
        both.update(env.agents)
        env.step({a: np.zeros(2, np.float32) for a in env.agents})
    env.close()
    assert both & buses
    with pytest.raises(ValueError, match="agent_classes must be SUMO vehicle classes"):
        CityEnvConfig(agent_classes=("lorry",))
