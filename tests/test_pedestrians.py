"""SUMO pedestrians on a pedestrian network (issue 14, item 3; ``ConvertOptions.pedestrians``).

Real scenes, real netconvert and SUMO: the default conversion is unchanged (the shipped bundle);
with pedestrians the network has sidewalks (lane 0) and crossings at the crosswalks while routes,
signals and quality figures still name the same vehicle lanes; recorded pedestrians are SUMO
persons at their recorded positions; a SUMO driver yields to a person on a real crossing.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR
from converters import load_scene
from converters.sumo.pedestrians import _axes
from converters.sumo.scenario import ConvertOptions, convert_scene, options_key
from magail_sumo.scene import ObjectType
from magail_sumo.sim.session import PERSON_PREFIX, Obstacles, SessionConfig, SumoSession

SHIPPED = ROOT / "networks" / "637f20cafde22ff8"


def _net_text(path) -> str:
    """A net file without netconvert's header line naming the time it was generated."""
    return "".join(ln for ln in open(path) if "generated on" not in ln)


def _convert(scene, out, **kw):
    rep = convert_scene(scene, out, ConvertOptions(**kw))
    assert rep.status == "ok", rep.reason
    folder = out / scene.scenario_id
    return folder, json.loads((folder / "conversion.json").read_text())


@pytest.fixture(scope="module")
def peds_637f(tmp_path_factory):
    scene = load_scene(WOMD_DIR / "637f20cafde22ff8.tfrecord")
    folder, rep = _convert(scene, tmp_path_factory.mktemp("peds"), pedestrians=True)
    return scene, folder, rep


@pytest.fixture(scope="module")
def peds_850c(tmp_path_factory):
    scene = load_scene(WOMD_DIR / "850c48d8bbfa008f.tfrecord")
    folder, rep = _convert(scene, tmp_path_factory.mktemp("peds"), pedestrians=True,
                           baseline=False)
    return scene, folder, rep


def _lanes(net_file):
    """SUMO lane id -> (allow attribute, womd_lane param or None) of the normal edges."""
    out = {}
    for edge in ET.parse(net_file).getroot().iter("edge"):
        if edge.get("function"):
            continue
        for lane in edge.iter("lane"):
            param = next((p.get("value") for p in lane.iter("param")
                          if p.get("key") == "womd_lane"), None)
            out[lane.get("id")] = (lane.get("allow"), param)
    return out


@pytest.mark.sumo
def test_default_conversion_is_unchanged(tmp_path, scene_637f):
    """Without the option the network is byte for byte the shipped one (made before it existed)
    and the options key is the one recorded then, so cached bundles stay valid."""
    folder, rep = _convert(scene_637f, tmp_path, baseline=False)
    assert _net_text(folder / "637f20cafde22ff8.net.xml") == \
        _net_text(SHIPPED / "637f20cafde22ff8.net.xml")
    for ext in ("rou", "edg", "con"):
        assert (folder / f"637f20cafde22ff8.{ext}.xml").read_bytes() == \
            (SHIPPED / f"637f20cafde22ff8.{ext}.xml").read_bytes(), ext
    assert "pedestrians" not in rep
    shipped = json.loads((SHIPPED / "conversion.json").read_text())
    assert options_key(ConvertOptions()) == shipped["options_key"]
    assert options_key(ConvertOptions(pedestrians=True)) != shipped["options_key"]
    assert ' allow="pedestrian"' not in (folder / "637f20cafde22ff8.net.xml").read_text()


@pytest.mark.sumo
def test_sidewalks_and_crossings_at_the_crosswalks(peds_637f):
    scene, folder, rep = peds_637f
    ped = rep["pedestrians"]
    assert ped["crosswalks"] == len(scene.roadmap.crosswalks) == 4
    assert ped["crossings"] == len(ped["crossing_list"]) >= 3
    assert ped["crossings"] + len(ped["dropped"]) == ped["crosswalks"]
    assert all(d["reason"] for d in ped["dropped"])
    root = ET.parse(folder / "637f20cafde22ff8.net.xml").getroot()
    crossings = {e.get("id"): e for e in root.iter("edge") if e.get("function") == "crossing"}
    assert len(crossings) == ped["crossings"]
    assert any(e.get("function") == "walkingarea" for e in root.iter("edge"))
    polys = {int(c.id): np.asarray(c.polygon)[:, :2] for c in scene.roadmap.crosswalks}
    for c in ped["crossing_list"]:  # each crossing lies on its crosswalk, over its edges
        edge = next(e for i, e in crossings.items() if i.startswith(f":{c['node']}_c")
                    and sorted(e.get("crossingEdges").split()) == c["edges"])
        shape = np.array([p.split(",") for p in edge.find("lane").get("shape").split()], float)
        centre, axis, half_len, half_wid = _axes(polys[c["crosswalk"]])
        across = (shape.mean(axis=0) - centre) @ np.array([-axis[1], axis[0]])
        assert abs(across) < half_wid + 3.0
    # sidewalks: lane 0 of road edges, pedestrians only; every vehicle lane keeps its WOMD lane
    lanes = _lanes(folder / "637f20cafde22ff8.net.xml")
    walks = [k for k, (allow, _) in lanes.items() if allow == "pedestrian"]
    assert len(walks) == ped["sidewalks"] > 50
    assert all(k.endswith("_0") for k in walks)
    default = _lanes(SHIPPED / "637f20cafde22ff8.net.xml")
    shifted = {k.rsplit("_", 1)[0] for k in walks}
    for k, (_, womd) in default.items():
        e, i = k.rsplit("_", 1)
        assert lanes[f"{e}_{int(i) + (e in shifted)}"][1] == womd, k


@pytest.mark.sumo
def test_routes_signals_and_quality_name_the_same_vehicle_lanes(peds_637f):
    """Lane indices shifted by the sidewalk: routes depart on the same WOMD lanes, the signal
    program (with the crossings' links) runs in SUMO and the quality figures are the default's."""
    scene, folder, rep = peds_637f
    shipped = json.loads((SHIPPED / "conversion.json").read_text())
    for key in ("on_network_rate", "route_rate", "signal_fidelity"):
        assert rep["quality"][key] == shipped["quality"][key], key
    assert rep["quality"]["sumo_baseline"]["collisions"] is not None  # SUMO ran the bundle
    lanes, default = _lanes(folder / "637f20cafde22ff8.net.xml"), _lanes(
        SHIPPED / "637f20cafde22ff8.net.xml")

    def departs(path):
        return {v.get("id"): f"{v.get('departEdge')}_{v.get('departLane')}"
                for v in ET.parse(path).getroot().iter("vehicle")}

    new, old = departs(folder / "637f20cafde22ff8.rou.xml"), departs(
        SHIPPED / "637f20cafde22ff8.rou.xml")
    assert new.keys() == old.keys()
    edges = {v.get("id"): v.find("route").get("edges").split()
             for v in ET.parse(folder / "637f20cafde22ff8.rou.xml").getroot().iter("vehicle")}
    for vid, lane in new.items():
        e, i = lane.rsplit("_", 1)
        sumo_lane = f"{edges[vid][int(e)]}_{i}" if e.isdigit() else lane
        oe, oi = old[vid].rsplit("_", 1)
        old_lane = f"{edges[vid][int(oe)]}_{oi}" if oe.isdigit() else old[vid]
        assert lanes[sumo_lane][0] != "pedestrian"
        assert lanes[sumo_lane][1] == default[old_lane][1], vid


@pytest.mark.sumo
def test_recorded_pedestrians_are_persons_at_their_positions(peds_637f, scene_637f):
    import libsumo as ls

    scene, folder, _ = peds_637f
    tr = scene.tracks
    rows = np.flatnonzero(tr.type == ObjectType.PEDESTRIAN)
    names = [str(int(i)) for i in tr.id[rows]]
    with SumoSession(folder / "637f20cafde22ff8.sumocfg") as sim:
        assert sim.walkable()
        obs = Obstacles(sim, names, tr.length[rows, 0], tr.width[rows, 0],
                        kinds=tr.type[rows])
        seen = set()
        for t in range(1, 30):
            ok = tr.valid[rows, t]
            x, y = np.where(ok, tr.x[rows, t], np.nan), np.where(ok, tr.y[rows, t], np.nan)
            obs.place(x, y, tr.heading[rows, t].astype(np.float64))
            sim.step()
            persons = obs.persons()
            assert set(ls.person.getIDList()) == set(persons.values())
            for k, name in enumerate(names):
                if name in persons:
                    seen.add(name)
                    assert persons[name].startswith(PERSON_PREFIX)
                    px, py = ls.person.getPosition(persons[name])
                    assert np.hypot(px - x[k], py - y[k]) < 1e-3, (name, t)
                    lane = ls.person.getLaneID(persons[name])
                    assert ls.lane.getAllowed(lane) == ("pedestrian",)
        assert len(seen) >= 3  # the pedestrians near the sidewalks and crossings
    # the same bundle converted without pedestrians has no persons: obstacles only
    with SumoSession(SHIPPED / "637f20cafde22ff8.sumocfg") as sim:
        assert not sim.walkable()
        obs = Obstacles(sim, names, tr.length[rows, 0], tr.width[rows, 0], kinds=tr.type[rows])
        obs.place(tr.x[rows, 1], tr.y[rows, 1], tr.heading[rows, 1].astype(np.float64))
        sim.step()
        assert ls.person.getIDList() == () and obs.persons() == {}


def _drive(folder, sid, route, lane, pos, person_at):
    """Steps until the vehicle reaches ``route[1]`` (or 12 s); (reached, stopped before)."""
    with SumoSession(net=folder / f"{sid}.net.xml",
                     config=SessionConfig(extra_args=("--no-internal-links", "false"))) as sim:
        ls = sim.api
        ls.route.add("r", route)
        ls.vehicle.add("v", "r", depart="now", departLane=str(lane), departPos=str(pos),
                       departSpeed="8")
        obs = None
        if person_at is not None:
            obs = Obstacles(sim, ["walker"], np.array([0.5]), np.array([0.5]),
                            kinds=np.array([ObjectType.PEDESTRIAN]))
            # the vehicle obstacle of the pedestrian must not be what stops the driver
            obs.threshold = 0.0
        stopped = False
        for _ in range(120):
            if obs is not None:
                obs.place(np.array([person_at[0]]), np.array([person_at[1]]), np.zeros(1))
            sim.step()
            if "v" not in ls.vehicle.getIDList():
                continue
            if ls.vehicle.getRoadID("v") == route[1]:
                return True, stopped
            stopped |= ls.vehicle.getSpeed("v") < 0.1
        return False, stopped


def _meet(path: np.ndarray, crossing: np.ndarray) -> np.ndarray | None:
    """The first point where polyline ``path`` meets polyline ``crossing`` (None: nowhere)."""
    for a, b in zip(path[:-1], path[1:]):
        for c, d in zip(crossing[:-1], crossing[1:]):
            m = np.array([b - a, c - d]).T
            if abs(np.linalg.det(m)) < 1e-9:
                continue
            t, u = np.linalg.solve(m, c - a)
            if 0.0 <= t <= 1.0 and 0.0 <= u <= 1.0:
                return a + t * (b - a)
    return None


@pytest.mark.sumo
def test_a_sumo_driver_yields_to_a_person_on_a_real_crossing(peds_850c):
    """A vehicle that drives through the junction unhindered stops before a crossing of its
    approach while a person stands on it (SUMO's junction model, a person placed by
    Obstacles)."""
    import sumolib

    scene, folder, rep = peds_850c
    sid = scene.scenario_id
    assert rep["pedestrians"]["crossings"] >= 1
    net = sumolib.net.readNet(str(folder / f"{sid}.net.xml"), withInternal=True)
    crossed = {e.get("id"): set(e.get("crossingEdges").split()) for e in
               ET.parse(folder / f"{sid}.net.xml").getroot().iter("edge")
               if e.get("function") == "crossing"}
    tried = 0
    for cid, edges in sorted(crossed.items()):
        shape = np.asarray(net.getLane(f"{cid}_0").getShape())
        node = net.getNode(cid[1:].rsplit("_c", 1)[0])
        for edge in node.getIncoming():  # approaches that cross it as they enter the junction
            if edge.getFunction() or edge.getID() not in edges:
                continue
            for conns in edge.getOutgoing().values():
                conn = conns[0]
                if conn.getFromLane().getPermissions() == {"pedestrian"}:
                    continue
                route, lane = [edge.getID(), conn.getTo().getID()], conn.getFromLane().getIndex()
                pos = max(edge.getLength() - 40.0, 0.0)
                if _drive(folder, sid, route, lane, pos, None) != (True, False):
                    continue  # it stops anyway (a minor road): nothing to learn about yielding
                tried += 1
                # the person stands where the vehicle's path through the junction meets it
                at = _meet(np.asarray(net.getLane(conn.getViaLaneID()).getShape()), shape)
                if at is None:
                    continue
                assert _drive(folder, sid, route, lane, pos, at) == (False, True), (cid, route)
                if tried >= 2:
                    return
    assert tried, "no approach of a crossing that a vehicle passes unhindered"


_APPEAR = """
import sys, numpy as np
from converters import load_scene
from magail_sumo.scene import ObjectType
from magail_sumo.sim.session import Obstacles, SumoSession
scene = load_scene(sys.argv[1])
tr = scene.tracks
rows = np.flatnonzero(tr.type == ObjectType.PEDESTRIAN)
k = int(np.flatnonzero(tr.id[rows] == 788)[0])
t0 = int(np.flatnonzero(tr.valid[rows[k]])[0])
with SumoSession(sys.argv[2]) as sim:
    obs = Obstacles(sim, [str(int(i)) for i in tr.id[rows]], tr.length[rows, 0],
                    tr.width[rows, 0], kinds=tr.type[rows])
    for t in range(1, t0 + 5):
        ok = tr.valid[rows, t]
        obs.place(np.where(ok, tr.x[rows, t], np.nan), np.where(ok, tr.y[rows, t], np.nan),
                  tr.heading[rows, t].astype(float))
        sim.step()
    pid = obs.persons()["788"]
    print(sim.api.person.getLaneID(pid), *sim.api.person.getPosition(pid),
          tr.x[rows[k], t0 + 4], tr.y[rows[k], t0 + 4])
"""


@pytest.mark.sumo
def test_a_pedestrian_appearing_on_a_walking_area(tmp_path):
    """A recorded pedestrian that appears on a walking area (2a1e44d405a6833f, track 788, among
    the scene's other pedestrians) is added on a sidewalk and moved there: SUMO crashed
    (segmentation fault) on a person departing inside the junction. Run in a subprocess so that
    a crash fails only this test."""
    import subprocess
    import sys

    scene = load_scene(ROOT / "data" / "scenarionet" / "2a1e44d405a6833f.pkl")
    folder, _ = _convert(scene, tmp_path, pedestrians=True, baseline=False)
    out = subprocess.run([sys.executable, "-c", _APPEAR,
                          str(ROOT / "data" / "scenarionet" / "2a1e44d405a6833f.pkl"),
                          str(folder / f"{scene.scenario_id}.sumocfg")],
                         capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-500:]
    lane, px, py, x, y = out.stdout.split()
    assert lane.startswith(":") and "_w" in lane  # on the walking area
    assert np.hypot(float(px) - float(x), float(py) - float(y)) < 1e-3


@pytest.mark.sumo
def test_env_and_sumo_baseline_walk_pedestrians_on_a_pedestrian_bundle(peds_637f):
    """The training env (SUMO background) and the ``sumo`` baseline pick the persons up from the
    bundle alone: persons at the recorded poses in the env; a rollout runs with them."""
    import libsumo as ls

    from magail_sumo.env import EnvConfig, SumoDrivingEnv, expert_actions
    from magail_sumo.evaluation import methods

    scene, folder, _ = peds_637f
    tr = scene.tracks
    env = SumoDrivingEnv(scene, folder, EnvConfig(controlled="sdc", background="sumo",
                                                  start_step=10, max_steps=5))
    try:
        env.reset(seed=0)
        env.step(expert_actions(env))
        persons = ls.person.getIDList()
        assert persons and all(p.startswith(PERSON_PREFIX) for p in persons)
        for p in persons:
            k = int(np.flatnonzero(tr.id == int(p[len(PERSON_PREFIX):].split("#")[0]))[0])
            assert tr.type[k] == ObjectType.PEDESTRIAN
            t = 11  # the log step SUMO shows after the reset at step 10 and one step
            assert np.hypot(*(np.array(ls.person.getPosition(p)) - [tr.x[k, t], tr.y[k, t]])) \
                < 1e-3
    finally:
        env.close()
    ro = methods.simulate(scene, "sumo", [0], bundle_dir=folder)
    assert np.isfinite(ro.x).all()


@pytest.mark.sumo
def test_cli_convert_pedestrians_is_its_own_cached_bundle(tmp_path, capsys):
    """``convert --pedestrians`` records the option (``pedestrians`` in conversion.json, its own
    options key): a rerun with it skips the scene, one without it converts the scene again."""
    from magail_sumo.cli.main import main

    sid, out = "850c48d8bbfa008f", tmp_path / "out"
    args = ["convert", str(WOMD_DIR / f"{sid}.tfrecord"), "--out", str(out), "--no-baseline"]

    def report():
        return json.loads((out / sid / "conversion.json").read_text())

    assert main(args + ["--pedestrians"]) == 0
    rep = report()
    assert rep["pedestrians"]["crossings"] == 3
    assert rep["options_key"] == options_key(ConvertOptions(pedestrians=True, baseline=False))
    capsys.readouterr()
    assert main(args + ["--pedestrians"]) == 0
    assert "0 scene(s), 1 skipped" in capsys.readouterr().err
    assert main(args) == 0
    assert "1 scene(s), 0 skipped" in capsys.readouterr().err
    assert "pedestrians" not in report()
