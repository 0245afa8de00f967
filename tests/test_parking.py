"""Non-moving vehicles in the SUMO files (converters.sumo.parking): plain ``sumo -c`` of a
bundle has SUMO's drivers respect them, and a parked car stands where it was recorded."""

from __future__ import annotations

import shutil
import subprocess
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from conftest import ROOT
from converters import load_scene
from converters.sumo import convert_scene
from converters.sumo.baseline import parked_boxes
from converters.sumo.parking import ParkedPose, box_segment_distance

#: real WOMD scene with 155 non-moving vehicles, most of them off the lanes
PARKING = ROOT / "data" / "scenarionet" / "4d320edc9cb801a3.pkl"


def test_box_segment_distance():
    pose = ParkedPose(0.0, 0.0, np.pi / 2, 4.0, 2.0)  # box along +y: x in [-1, 1], y in [-2, 2]
    a = np.array([[-5.0, 0.0], [3.0, -9.0], [0.0, 0.5], [2.0, 3.0]])
    b = np.array([[5.0, 0.0], [3.0, 9.0], [0.2, 0.7], [4.0, 3.0]])
    # through the box with both ends outside; 2 m to its side; inside; off its corner (1, 2)
    assert np.allclose(box_segment_distance(pose, a, b), [0.0, 2.0, 0.0, np.hypot(1.0, 1.0)])


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    scene = load_scene(PARKING)
    out = tmp_path_factory.mktemp("parking")
    rep = convert_scene(scene, out)
    assert rep.status == "ok", rep.reason
    return scene, out / scene.scenario_id, rep


@pytest.mark.sumo
def test_every_non_moving_vehicle_is_in_the_sumo_files(converted):
    scene, folder, rep = converted
    rows, ids = parked_boxes(scene)
    assert len(rows) > 100
    root = ET.parse(folder / f"{scene.scenario_id}.rou.xml").getroot()
    stops = {v.get("id"): v.find("stop") for v in root.iter("vehicle")
             if v.find("stop") is not None}
    left_out = {str(u["id"]) for u in rep.unconverted if u["reason"].startswith("parked")}
    assert set(ids) == set(stops) | left_out and not left_out & set(stops)
    blocking = [i for i, s in stops.items() if s.get("parking") == "false"]
    spaces = [i for i, s in stops.items() if s.get("parkingArea") == f"park_{i}"]
    assert len(blocking) + len(spaces) == len(stops) and blocking and spaces
    add = ET.parse(folder / f"{scene.scenario_id}.parking.add.xml").getroot()
    assert {p.get("id") for p in add.iter("parkingArea")} == {f"park_{i}" for i in spaces}
    assert f"{scene.scenario_id}.parking.add.xml" in rep.files


@pytest.mark.sumo
def test_plain_sumo_drivers_do_not_touch_the_parked_vehicles(converted):
    """The converter's own run of ``sumo -c`` (conversion.json): no SUMO-driven vehicle's box
    overlaps a recorded non-moving vehicle's, SUMO counts no collision, and the sumo binary
    runs the bundle without an error."""
    scene, folder, rep = converted
    base = rep.quality["sumo_baseline"]
    assert base["parked_overlaps"] == 0 and base["collisions"] == 0
    out = subprocess.run([shutil.which("sumo"), "-c", f"{scene.scenario_id}.sumocfg",
                          "--no-step-log", "true"], cwd=folder, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0 and "Error" not in out.stderr, out.stderr


@pytest.mark.sumo
def test_a_parked_car_stands_where_it_was_recorded(converted):
    """SUMO reports a vehicle's front bumper and navigation angle: a car in a parking space is
    at its recorded box's front, facing its recorded heading."""
    import libsumo

    from converters.sumo.parking import parked_pose

    scene, folder, _ = converted
    add = ET.parse(folder / f"{scene.scenario_id}.parking.add.xml").getroot()
    ids = [p.get("id").removeprefix("park_") for p in add.iter("parkingArea")][:20]
    libsumo.start(["sumo", "-c", str(folder / f"{scene.scenario_id}.sumocfg"),
                   "--no-step-log", "true"])
    try:
        for _ in range(3):
            libsumo.simulationStep()
        row_of = {str(int(t)): k for k, t in enumerate(scene.tracks.id.tolist())}
        for vid in ids:
            assert libsumo.vehicle.isStoppedParking(vid)
            pose = parked_pose(scene, row_of[vid])
            x, y = libsumo.vehicle.getPosition(vid)
            front = (pose.x + pose.length / 2 * np.cos(pose.heading),
                     pose.y + pose.length / 2 * np.sin(pose.heading))
            assert np.hypot(x - front[0], y - front[1]) < 0.02
            nav = (90.0 - np.degrees(pose.heading)) % 360.0
            assert abs((libsumo.vehicle.getAngle(vid) - nav + 180) % 360 - 180) < 0.2
    finally:
        libsumo.close()


@pytest.mark.sumo
def test_without_the_parked_vehicles_sumo_drivers_run_into_them(tmp_path):
    """637f20cafde22ff8: with its non-moving vehicles in the SUMO files, no SUMO driver touches
    one; with them taken out of the routes (as the converter left most of them out before),
    SUMO's drivers pass through recorded cars that stand on their lanes."""
    from converters.sumo.baseline import run_baseline

    scene = load_scene(ROOT / "data" / "womd" / "637f20cafde22ff8.tfrecord")
    rep = convert_scene(scene, tmp_path)
    assert rep.quality["sumo_baseline"]["parked_overlaps"] == 0
    folder = tmp_path / scene.scenario_id
    routes = folder / f"{scene.scenario_id}.rou.xml"
    tree = ET.parse(routes)
    root = tree.getroot()
    for v in [v for v in root.findall("vehicle") if v.find("stop") is not None]:
        root.remove(v)
    tree.write(routes)
    cfg = folder / f"{scene.scenario_id}.sumocfg"
    cfg.write_text(cfg.read_text().replace(f"{scene.scenario_id}.parking.add.xml,", ""))
    assert run_baseline(scene, str(cfg), [], None).parked_overlaps > 0
