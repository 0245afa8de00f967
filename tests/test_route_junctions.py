"""Routes reach into the junctions netconvert builds over mapped lanes (issue 14, item 4)."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest
import sumolib

from conftest import WOMD_DIR
from converters import load_scene
from converters.sumo.quality import lane_segments, on_lanes
from converters.sumo.routes import _via_edges
from converters.sumo.scenario import ConvertOptions, convert_scene


@pytest.mark.sumo
def test_route_starts_in_the_junction_its_track_starts_in(tmp_path):
    """2831b6fde0420b0d: vehicles whose track starts inside the junction before their first
    mapped edge (netconvert's junction covers that part of the lane) get the edge before it in
    their route and depart on the next one, so the route covers their first states; every
    departure names a lane of its departure edge."""
    scene = load_scene(WOMD_DIR / "2831b6fde0420b0d.tfrecord")
    rep = convert_scene(scene, tmp_path, ConvertOptions(baseline=False))
    assert rep.status == "ok" and rep.quality["route_rate"] == 1.0
    folder = tmp_path / scene.scenario_id
    net = sumolib.net.readNet(str(folder / f"{scene.scenario_id}.net.xml"), withInternal=True)
    seg = lane_segments(net)
    tr = scene.tracks
    extended = 0
    for v in ET.parse(folder / f"{scene.scenario_id}.rou.xml").getroot().iter("vehicle"):
        edges = v.find("route").get("edges").split()
        k = int(v.get("departEdge"))
        assert k < len(edges) and int(v.get("departLane")) < net.getEdge(edges[k]).getLaneNumber()
        if k == 1:
            n = int(np.flatnonzero(tr.id == int(v.get("id")))[0])
            s = int(np.argmax(tr.valid[n]))
            mask = np.isin(seg.edge, list(_via_edges(net, edges[0], edges[1])))
            assert on_lanes(seg, np.array([[tr.x[n, s], tr.y[n, s]]]),
                            np.array([float(tr.heading[n, s])]), mask)[0], v.get("id")
            extended += 1
    assert extended >= 3
