"""GPUDrive / Nocturne JSON scenes (converters/gpudrive): read, round-trip, refuse what is bad,
registered as a scene format (inspect, pools, convert), on the bundled real file and the
../shared ones when present."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR
from converters import load_scene
from converters.gpudrive import load_gpudrive, scene_to_gpudrive, write_gpudrive
from converters.scene_files import RecordRef, detect_format, list_records, read_record
from magail_sumo.errors import SceneFormatError
from magail_sumo.scene import LaneType, ObjectType, RoadEdgeType

FILE = ROOT / "data" / "gpudrive" / "tfrecord-00002-of-01000_407.json"
SHARED = ROOT.parent / "shared" / "data" / "gpudrive"
FILES = [FILE] + (sorted(f for f in SHARED.glob("*.json") if f.name != FILE.name)
                  if SHARED.is_dir() else [])


def test_reads_the_bundled_real_scene():
    s = load_gpudrive(FILE)
    raw = json.loads(FILE.read_text())
    assert s.scenario_id == "bada21415c031740" == raw["scenario_id"]
    assert s.num_steps == 91 and s.current_time_index == 10
    assert s.tracks.num_tracks == 15 and set(s.tracks.type.tolist()) == {int(ObjectType.VEHICLE)}
    assert s.sdc_track_index == 14 and len(s.tracks_to_predict) == 2
    o = raw["objects"][3]
    k = int(np.flatnonzero(s.tracks.id == o["id"])[0])
    assert s.tracks.x[k, 5] == o["position"][5]["x"] and s.tracks.heading[k, 5] == \
        np.float32(o["heading"][5])
    assert s.tracks.valid[k].tolist() == o["valid"] and s.tracks.length[k, 0] == \
        np.float32(o["length"])
    counts = s.roadmap.count_by_kind()
    assert counts["lane"] == 76 and counts["road_edge"] == 28 and counts["driveway"] == 47
    assert {l.type for l in s.roadmap.lanes} <= {LaneType.SURFACE_STREET, LaneType.BIKE_LANE}
    assert {e.type for e in s.roadmap.road_edges} == {RoadEdgeType.BOUNDARY}
    dq = s.data_quality.to_dict()["inferred_connectivity"]
    assert dq["successors"] > 50 and dq["neighbors"] > 0  # the format has no connectivity


def test_round_trip_of_any_scene(tmp_path):
    """A WOMD scene (with signals) and the JSON scene itself survive JSON and back: tracks,
    map geometry and types, signals and metadata (box sizes: the median per track)."""
    for scene in (load_scene(WOMD_DIR / "637f20cafde22ff8.tfrecord"), load_gpudrive(FILE)):
        back = load_gpudrive(write_gpudrive(scene, tmp_path / f"{scene.scenario_id}.json"))
        a, b = scene.tracks, back.tracks
        for f in ("id", "type", "x", "y", "z", "heading", "vx", "vy", "valid"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
        for x, y in ((scene.roadmap.lanes, back.roadmap.lanes),
                     (scene.roadmap.road_edges, back.roadmap.road_edges),
                     (scene.roadmap.road_lines, back.roadmap.road_lines),
                     (scene.roadmap.crosswalks, back.roadmap.crosswalks)):
            assert [(f.id, f.type if hasattr(f, "type") else None) for f in x] == \
                [(f.id, f.type if hasattr(f, "type") else None) for f in y]
            for f, g in zip(x, y):
                np.testing.assert_array_equal(getattr(f, "polyline", getattr(f, "polygon", 0)),
                                              getattr(g, "polyline", getattr(g, "polygon", 0)))
        assert (back.sdc_track_index, back.current_time_index, back.tracks_to_predict,
                back.objects_of_interest) == (scene.sdc_track_index, scene.current_time_index,
                                              scene.tracks_to_predict, scene.objects_of_interest)
        np.testing.assert_array_equal(back.signals.state, scene.signals.state)
        np.testing.assert_array_equal(back.signals.lane, scene.signals.lane)
        np.testing.assert_array_equal(back.signals.step, scene.signals.step)


def _bad(tmp_path, doc) -> str:
    path = tmp_path / "bad.json"
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    with pytest.raises(SceneFormatError) as err:
        load_gpudrive(path)
    msg = str(err.value)
    assert "\n" not in msg and "bad.json" in msg
    return msg


def test_bad_documents_are_one_line_naming_the_field(tmp_path):
    doc = json.loads(FILE.read_text())
    assert "objects: expected a list" in _bad(tmp_path, {**doc, "objects": {}})
    short = json.loads(FILE.read_text())
    short["objects"][2]["heading"] = short["objects"][2]["heading"][:50]
    assert "objects[2]: heading / valid have 50 / 91 steps" in _bad(tmp_path, short)
    bad_point = json.loads(FILE.read_text())
    bad_point["objects"][1]["position"][7] = {"x": "east", "y": 0}
    assert "objects[1].position[7].x: expected a number" in _bad(tmp_path, bad_point)
    dup = json.loads(FILE.read_text())
    dup["objects"][1]["id"] = dup["objects"][0]["id"]
    assert "used by more than one object" in _bad(tmp_path, dup)
    sdc = json.loads(FILE.read_text())
    sdc["metadata"]["sdc_track_index"] = 99
    assert "metadata.sdc_track_index: 99 is not an object index" in _bad(tmp_path, sdc)
    assert "not valid JSON" in _bad(tmp_path, "{\"objects\": [")
    assert "JSON nested deeper than 16 levels" in _bad(tmp_path, "[" * 50 + "]" * 50)
    dev = tmp_path / "zero.json"
    dev.symlink_to("/dev/zero")
    with pytest.raises(SceneFormatError, match="zero.json: .*is a character device"):
        load_gpudrive(dev)


def test_other_schema_details_are_accepted(tmp_path):
    """Nocturne-style points as lists, no z, no velocity (derived), unknown road types noted,
    per-lane signal state series."""
    doc = json.loads(FILE.read_text())
    for o in doc["objects"]:
        o["position"] = [[p["x"], p["y"]] for p in o["position"]]
        del o["velocity"], o["height"]
    doc["roads"].append({"id": 99999, "type": "parking_lot", "geometry": [[0, 0], [1, 1]]})
    lane = next(r["id"] for r in doc["roads"] if r["type"] == "lane")
    doc["tl_states"] = {str(lane): {"state": ["LANE_STATE_STOP"] * 91}}
    path = tmp_path / "nocturne.json"
    path.write_text(json.dumps(doc))
    s = load_gpudrive(path)
    ref = load_gpudrive(FILE)
    np.testing.assert_array_equal(s.tracks.x, ref.tracks.x)
    assert np.all(s.tracks.z == 0)
    k = int(np.argmax(ref.tracks.valid.sum(axis=1)))
    v = ref.tracks.valid[k]
    speed = np.hypot(s.tracks.vx[k, v], s.tracks.vy[k, v])
    ref_speed = np.hypot(ref.tracks.vx[k, v], ref.tracks.vy[k, v])
    assert np.median(np.abs(speed - ref_speed)) < 0.3  # derived from positions
    notes = " | ".join(s.data_quality.notes)
    assert "velocity derived from positions" in notes and "'parking_lot' skipped" in notes
    assert len(s.signals) == 91 and set(s.signals.lane.tolist()) == {lane}


def test_registered_as_a_scene_format(tmp_path):
    from magail_sumo.env.scene_pool import resolve_pool

    assert detect_format(FILE) == "gpudrive"
    assert list_records(FILE) == [RecordRef(str(FILE), 0)]
    assert read_record(RecordRef(str(FILE), 0)).scenario_id == "bada21415c031740"
    assert [Path(r.path).name for r in resolve_pool([str(FILE.parent)])] == [FILE.name]
    assert scene_to_gpudrive(load_gpudrive(FILE))["scenario_id"] == "bada21415c031740"


@pytest.mark.sumo
@pytest.mark.parametrize("path", FILES, ids=lambda p: p.stem)
def test_converts_meeting_the_route_and_network_bars(path, tmp_path):
    from converters.sumo.scenario import ConvertOptions, convert_scene

    rep = convert_scene(load_gpudrive(path), tmp_path, ConvertOptions(baseline=False))
    assert rep.status == "ok", rep.reason
    assert rep.quality["route_rate"] >= 0.95 and rep.quality["on_network_rate"] >= 0.98
