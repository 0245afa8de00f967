"""Issue 14: real ScenarioNet pickles of both layouts and of non-WOMD datasets (nuScenes).

The real files in data/scenarionet/ are tested unconditionally; every file of
../shared/data/scenarionet/ (or $MAGAIL_SUMO_SHARED_DATA/scenarionet/) when present.
"""

from __future__ import annotations

import json
import os
import pickle
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT
from converters.scenarionet import (
    load_scenarionet, safe_loads, scene_to_scenarionet, write_scenarionet,
)
from converters.sumo import ConvertOptions, convert_scene
from magail_sumo.scene import Lane, SignalState, infer_lane_connectivity
from test_cli import run_cli

BUNDLED = ROOT / "data" / "scenarionet"
OLDER = BUNDLED / "250011f460de6135.pkl"  # older MetaDrive layout: state.size, areas as polylines
NO_META = BUNDLED / "8799c31b5be1f312.pkl"  # older layout without metadata, int keys, signals
NUSCENES = BUNDLED / "sd_nuscenes_v1.0-mini_scene-0757.pkl"  # string ids, no connectivity
SHARED = Path(os.environ.get("MAGAIL_SUMO_SHARED_DATA", ROOT.parent / "shared" / "data")) \
    / "scenarionet"
SHARED_FILES = sorted(SHARED.glob("*/*.pkl")) if SHARED.is_dir() else []


def _round_trip(path: Path, tmp_path: Path):
    scene = load_scenarionet(path)
    out = write_scenarionet(tmp_path / "rt.pkl", scene)
    back = load_scenarionet(out)
    assert back == scene, scene.differences(back)
    assert back.data_quality.dropped_references == ()  # nothing left to repair
    return scene


@pytest.mark.parametrize("path", sorted(BUNDLED.glob("*.pkl")), ids=lambda p: p.stem)
def test_bundled_real_files_read_and_round_trip(path, tmp_path):
    scene = _round_trip(path, tmp_path)
    assert scene.tracks.valid.any() and scene.roadmap.lanes


@pytest.mark.parametrize("path", SHARED_FILES, ids=lambda p: p.stem)
def test_shared_real_files_read_and_round_trip(path, tmp_path):
    _round_trip(path, tmp_path)


def test_shared_files_are_present_or_skipped():
    if not SHARED_FILES:
        pytest.skip("no shared ScenarioNet data")
    assert len(SHARED_FILES) >= 18


def test_older_layout_sizes_and_areas_without_polygon():
    scene = load_scenarionet(OLDER)
    sd = safe_loads(OLDER.read_bytes())
    key = next(iter(sd["tracks"]))
    size = sd["tracks"][key]["state"]["size"]
    tr = scene.tracks
    np.testing.assert_array_equal(tr.length[0], size[:, 0].astype(np.float32))
    np.testing.assert_array_equal(tr.width[0], size[:, 1].astype(np.float32))
    np.testing.assert_array_equal(tr.height[0], size[:, 2].astype(np.float32))
    assert scene.sdc_track_index == list(sd["tracks"]).index(sd["metadata"]["sdc_id"])
    bumps = scene.roadmap.speed_bumps
    assert len(bumps) == 5 and all(b.polygon.shape[0] >= 3 for b in bumps)  # from "polyline"


def test_no_metadata_top_level_sdc_and_integer_signal_codes():
    sd = safe_loads(NO_META.read_bytes())
    assert "metadata" not in sd and "length" not in sd
    scene = load_scenarionet(NO_META)
    assert scene.num_steps == len(sd["ts"]) == 198
    # top-level sdc_track_index is a track key in this layout
    assert int(scene.tracks.id[scene.sdc_track_index]) == sd["sdc_track_index"]
    assert scene.roadmap.count_by_kind()["crosswalk"] == 4  # "CROSS_WALK"
    sig = scene.signals
    assert len(sig) == 6 and set(sig.step.tolist()) == {197}
    assert set(sig.state.tolist()) == {SignalState.STOP}  # WOMD code 4
    assert set(sig.lane.tolist()) == {47, 134, 135, 136, 137, 138}
    assert np.all(np.abs(sig.stop_point[:, :2]) > 1)
    assert "1 of 198 steps" in scene.data_quality.notes[0]


def test_string_track_ids_are_numbered_and_written_back():
    sd = safe_loads(NUSCENES.read_bytes())
    scene = load_scenarionet(NUSCENES)
    keys = list(sd["tracks"])
    np.testing.assert_array_equal(scene.tracks.id, np.arange(len(keys)))
    assert [name for _, name in scene.source_ids.tracks] == keys
    assert keys[scene.sdc_track_index] == "ego"
    out = scene_to_scenarionet(scene)
    assert list(out["tracks"]) == keys and out["metadata"]["sdc_id"] == "ego"
    assert list(out["map_features"]) == list(sd["map_features"])
    assert scene.tracks.count_by_type()["other"] == 5  # traffic cones


def test_connectivity_inferred_for_a_map_without_any():
    scene = load_scenarionet(NUSCENES)
    dq = scene.data_quality
    assert dq.inferred_successors > 100 and dq.inferred_neighbors > 10
    lanes = scene.roadmap.lanes
    assert sum(len(l.exit_lanes) for l in lanes) == dq.inferred_successors
    assert sum(len(l.entry_lanes) for l in lanes) == dq.inferred_successors
    # every inferred successor starts where its predecessor ends
    by_id = {l.id: l for l in lanes}
    for lane in lanes:
        for nxt in lane.exit_lanes:
            assert np.linalg.norm(lane.polyline[-1, :2] - by_id[nxt].polyline[0, :2]) <= 1.5
    # a WOMD map with connectivity gets nothing inferred
    assert load_scenarionet(OLDER).data_quality.inferred_successors == 0


def test_lanes_recorded_without_links_are_joined_and_their_signals_mapped(tmp_path):
    """8799c31b5be1f312 (older MetaDrive layout): signalled junction lane 136 comes with no
    entry or exit lane although its ends meet lanes 92 and 132 exactly, so no SUMO link carried
    its signal (signal fidelity 0.833). The converter joins such lanes by geometry, only them
    (the scene stays as recorded; the repair is reported), and replays every recorded signal
    state."""
    from converters.sumo import convert_scene
    from converters.sumo.topology import plan_network

    scene = load_scenarionet(NO_META)
    lane = next(l for l in scene.roadmap.lanes if l.id == 136)
    assert lane.entry_lanes == lane.exit_lanes == ()  # as recorded
    plan = plan_network(scene)
    assert plan.linked[136] == ((92,), (132,))
    rep = convert_scene(scene, tmp_path)
    assert rep.status == "ok", rep.reason
    assert rep.quality["signal_fidelity"] >= 0.99 and rep.quality["signal_misses"] == []
    assert any("lanes recorded without any entry or exit lane" in n
               for n in rep.data_quality["notes"])


def _straight(lid, x0, y0, x1, y1, n=11):
    return Lane(lid, np.stack([np.linspace(x0, x1, n), np.linspace(y0, y1, n), np.zeros(n)], 1))


def test_infer_lane_connectivity_geometry():
    lanes = [
        _straight(1, 0, 0, 10, 0),
        _straight(2, 10.5, 0, 20, 0),  # successor of 1 (0.5 m gap, same heading)
        _straight(3, 0, 3.5, 10, 3.5),  # left neighbour of 1
        _straight(4, 10, -3.5, 0, -3.5),  # opposite direction: not a neighbour
        _straight(5, 13, 0, 13, 10),  # starts 3 m from 1's end, turned 90°: not a successor
        _straight(6, 10, 0.2, 10, 10),  # starts at 1's end but turned 90°: not a successor
    ]
    out, succ, nbs = infer_lane_connectivity(lanes)
    by_id = {l.id: l for l in out}
    assert by_id[1].exit_lanes == (2,) and by_id[2].entry_lanes == (1,) and succ == 1
    assert [n.feature_id for n in by_id[1].left_neighbors] == [3]
    assert [n.feature_id for n in by_id[3].right_neighbors] == [1]
    assert by_id[1].right_neighbors == () and by_id[4].left_neighbors == ()
    assert by_id[1].left_neighbors[0].self_end_index == 10
    assert [n.feature_id for n in by_id[6].right_neighbors] == [5]  # 3 m apart, both north
    assert nbs == 4
    none, s0, n0 = infer_lane_connectivity(lanes, successors=False, neighbors=False)
    assert (s0, n0) == (0, 0) and all(not l.exit_lanes for l in none)


def _dangling_file(tmp_path: Path) -> Path:
    """The older-layout scene (as we write it) with references to ids not in its map."""
    sd = scene_to_scenarionet(load_scenarionet(OLDER))
    feats = sd["map_features"]
    lane_key = next(k for k, f in feats.items() if f["type"].startswith("LANE_")
                    and len(f["polyline"]) > 2)
    lane = feats[lane_key]
    lane["right_neighbor"] = list(lane["right_neighbor"]) + [{
        "feature_id": "99999", "self_start_index": 0, "self_end_index": 1,
        "neighbor_start_index": 0, "neighbor_end_index": 1, "boundaries": []}]
    lane["exit_lanes"] = list(lane["exit_lanes"]) + [88888]
    lane["left_boundaries"] = list(lane["left_boundaries"]) + [{
        "lane_start_index": 0, "lane_end_index": 1, "boundary_type": "UNKNOWN",
        "boundary_feature_id": 77777}]
    sign = next(f for f in feats.values() if f["type"] == "STOP_SIGN")
    sign["lane"] = list(sign["lane"]) + [66666]
    path = tmp_path / "dangling.pkl"
    path.write_bytes(pickle.dumps(sd, protocol=4))
    return path


def test_dangling_references_keep_the_scene_and_are_listed(tmp_path):
    path = _dangling_file(tmp_path)
    scene = load_scenarionet(path)
    dropped = {(r.field, r.missing_id) for r in scene.data_quality.dropped_references}
    assert dropped == {("right_neighbor", "99999"), ("exit_lanes", "88888"),
                       ("left_boundaries", "77777"), ("lane", "66666")}
    assert scene == load_scenarionet(OLDER)  # the same scene once the references are dropped
    out = run_cli("inspect", "--json", path)
    assert out.returncode == 0, out.stderr
    rec = json.loads(out.stdout)
    assert len(rec["data_quality"]["dropped_references"]) == 4
    text = run_cli("inspect", path).stdout
    assert "dropped refs      4" in text and "right_neighbor -> 99999" in text


@pytest.mark.sumo
def test_bundled_files_convert(tmp_path):
    """Real netconvert; the dangling-reference scene lists its repairs in conversion.json."""
    scenes = [load_scenarionet(_dangling_file(tmp_path)), load_scenarionet(NO_META),
              load_scenarionet(NUSCENES)]
    for scene in scenes:
        rep = convert_scene(scene, tmp_path / "out", ConvertOptions(baseline=False))
        assert rep.status == "ok", rep.reason
        assert rep.quality["on_network_rate"] > 0.8, rep.quality
    conv = json.loads((tmp_path / "out" / "250011f460de6135" / "conversion.json").read_text())
    assert len(conv["data_quality"]["dropped_references"]) == 4
    nus = json.loads((tmp_path / "out" / "scene-0757" / "conversion.json").read_text())
    inferred = nus["data_quality"]["inferred_connectivity"]
    assert inferred["successors"] > 100 and inferred["neighbors"] > 10


def test_source_ids_are_compared_and_validated():
    import dataclasses

    from magail_sumo.scene import DataQuality, SceneValidationError, SourceIds, validate_scene
    scene = load_scenarionet(NUSCENES)
    assert dataclasses.replace(scene, data_quality=DataQuality()) == scene  # not compared
    assert dataclasses.replace(scene, source_ids=SourceIds()) != scene  # compared
    pairs = scene.source_ids.tracks
    twice = SourceIds(pairs[:-1] + ((pairs[-1][0], pairs[0][1]),), scene.source_ids.map_features)
    with pytest.raises(SceneValidationError, match="appears twice"):
        validate_scene(dataclasses.replace(scene, source_ids=twice))
    unknown = SourceIds(pairs + ((10**6, "x"),), ())
    with pytest.raises(SceneValidationError, match="track id 1000000 does not exist"):
        validate_scene(dataclasses.replace(scene, source_ids=unknown))


def test_inference_skipped_above_the_lane_limit(monkeypatch):
    from converters.scenarionet import reader
    sd = scene_to_scenarionet(load_scenarionet(NUSCENES))
    for f in sd["map_features"].values():
        for key in ("entry_lanes", "exit_lanes", "left_neighbor", "right_neighbor"):
            if key in f:
                f[key] = []
    assert reader.scene_from_scenarionet(sd).data_quality.inferred_successors > 100
    monkeypatch.setattr(reader, "MAX_INFERRED_LANES", 10)
    scene = reader.scene_from_scenarionet(sd)
    assert scene.data_quality.inferred_successors == 0
    assert "none inferred" in scene.data_quality.notes[0]


@pytest.mark.parametrize("field, value, message", [
    ("object_state", 9, "unknown signal state code 9"),
    ("lane", 1.5, "expected an integer, got 1.5"),
])
def test_older_layout_bad_signal_arrays_are_named(field, value, message):
    from converters.scenarionet import reader
    from magail_sumo.scene import SceneValidationError
    sd = safe_loads(NO_META.read_bytes())
    light = sd["dynamic_map_states"]["47"]["state"]
    arr = np.asarray(light[field], dtype=np.float64 if isinstance(value, float) else np.int64)
    arr[197] = value
    light[field] = arr
    with pytest.raises(SceneValidationError, match=message) as err:
        reader.scene_from_scenarionet(sd)
    assert "dynamic_map_states['47'].state" in str(err.value)


def test_sideways_recording_vehicle_box_is_set_upright():
    """ScenarioNet's nuScenes ego is 1.73 m long and 4.08 m wide in the pickle
    (metadriverse/scenarionet#68): the reader swaps the two for the recording vehicle only and
    says so; a WOMD scene's boxes are kept as recorded."""
    raw = safe_loads(NUSCENES.read_bytes())
    sdc_key = raw["metadata"]["sdc_id"]
    state = {k: np.asarray(raw["tracks"][sdc_key]["state"][k], np.float32).reshape(-1)
             for k in ("length", "width")}
    scene = load_scenarionet(NUSCENES)
    i, tr = scene.sdc_track_index, scene.tracks
    v = tr.valid[i]
    assert np.median(state["length"][v]) < np.median(state["width"][v])  # as shipped
    assert np.array_equal(tr.length[i], state["width"])
    assert np.array_equal(tr.width[i], state["length"])
    assert any("length and width swapped" in n for n in scene.data_quality.notes)
    for key, k in ((key, k) for k, key in enumerate(raw["tracks"]) if key != sdc_key):
        recorded = np.asarray(raw["tracks"][key]["state"]["length"], np.float32).reshape(-1)
        assert np.array_equal(tr.length[k], recorded), key  # kept as recorded
        break
    womd = load_scenarionet(OLDER)
    assert not any("swapped" in n for n in womd.data_quality.notes)


def test_synthetic_track_is_dropped_unless_kept(tmp_path):
    """A track named by metadata.selected_adv_id (a generated adversary) is not human driving:
    dropped by default with a note, every reference to it kept consistent; kept on request."""
    from converters.scenarionet import scene_from_scenarionet

    path = BUNDLED / "2a1e44d405a6833f.pkl"  # newer layout, with tracks to predict
    sd = safe_loads(path.read_bytes())
    base = scene_from_scenarionet(sd)
    ttp = base.tracks_to_predict
    adv = ttp[0].track_index  # a track to predict becomes the "adversary"
    adv_id = int(base.tracks.id[adv])
    sd["metadata"]["selected_adv_id"] = str(adv_id)
    sd["metadata"]["objects_of_interest"] = [str(adv_id)]
    dropped = scene_from_scenarionet(sd)
    assert dropped.tracks.num_tracks == base.tracks.num_tracks - 1
    assert adv_id not in dropped.tracks.id.tolist() and dropped.objects_of_interest == ()
    assert len(dropped.tracks_to_predict) == len(ttp) - 1
    for p in dropped.tracks_to_predict:  # renumbered: still the same tracks
        assert int(dropped.tracks.id[p.track_index]) in base.tracks.id[[q.track_index
                                                                        for q in ttp]]
    sdc_id = int(base.tracks.id[base.sdc_track_index])
    assert int(dropped.tracks.id[dropped.sdc_track_index]) == sdc_id
    assert any(f"synthetic track(s) {adv_id}" in n and "dropped" in n
               for n in dropped.data_quality.notes)
    kept = scene_from_scenarionet(sd, keep_synthetic=True)
    assert kept.tracks.num_tracks == base.tracks.num_tracks
    assert any("kept on request" in n for n in kept.data_quality.notes)
    plain = scene_to_scenarionet(base)  # plain numpy: a file as a converter would write it
    plain["metadata"]["selected_adv_id"] = str(adv_id)
    out = tmp_path / "adv.pkl"
    with open(out, "wb") as fh:
        pickle.dump(plain, fh)
    assert "synthetic track(s)" in run_cli("inspect", out).stdout
    assert "kept on request" in run_cli("inspect", "--keep-synthetic", out).stdout


@pytest.mark.parametrize("path", [p for p in SHARED_FILES if "womd_metavqa" in str(p)][:5],
                         ids=lambda p: p.stem)
def test_shared_adversarial_scenes_lose_their_generated_track(path):
    from converters.scenarionet import load_scenarionet

    scene, kept = load_scenarionet(path), load_scenarionet(path, keep_synthetic=True)
    assert scene.tracks.num_tracks == kept.tracks.num_tracks - 1
    assert "dropped: not human driving" in scene.data_quality.notes[-1]


def test_lane_centre_lines_in_another_frame_are_moved_onto_their_polygons():
    """ScenarioNet's nuScenes trainval pickles give the centre lines of lanes with a polygon in
    a frame centred on the ego's first position, everything else in the map frame: the reader
    moves them back by the common offset and says so. Made here from the bundled mini scene
    (whose frames agree) by shifting those centre lines as the trainval files have them."""
    from converters.scenarionet import scene_from_scenarionet

    raw = safe_loads(NUSCENES.read_bytes())
    base = scene_from_scenarionet(raw)
    assert not any("off their own polygons" in n for n in base.data_quality.notes)
    shift = np.array([705.31, 1578.91])
    moved = [k for k, f in raw["map_features"].items()
             if "LANE" in str(f["type"]) and f.get("polygon") is not None]
    assert len(moved) > 20
    for k in moved:
        line = np.array(raw["map_features"][k]["polyline"], np.float64)
        line[:, :2] -= shift
        raw["map_features"][k]["polyline"] = line
    fixed = scene_from_scenarionet(raw)
    note = [n for n in fixed.data_quality.notes if "off their own polygons" in n]
    assert note and note[0].startswith(f"{len(moved)} lane centre lines lay (705.")
    # no lane links in the mini scene: the offset is the polygons' estimate, within 0.5 m
    for a, b in zip(base.roadmap.lanes, fixed.roadmap.lanes):
        assert np.allclose(a.polyline, b.polyline, atol=0.5), a.id


def test_a_bad_lane_polygon_does_not_refuse_the_scene():
    """A lane's polygon is read only for the frame check: one that is not a point list leaves
    that lane unchecked and the scene reads as before (it was ignored before the check)."""
    from converters.scenarionet import scene_from_scenarionet

    raw = safe_loads(NUSCENES.read_bytes())
    base = scene_from_scenarionet(raw)
    key = next(k for k, f in raw["map_features"].items()
               if "LANE" in str(f["type"]) and f.get("polygon") is not None)
    raw["map_features"][key]["polygon"] = "not points"
    assert scene_from_scenarionet(raw) == base


@pytest.mark.parametrize("name", ["scene-0425", "scene-1044"])
def test_shared_nuscenes_trainval_scene_converts_within_its_bars(name, tmp_path):
    """Two real nuScenes trainval scenes that failed before: every lane link joined lanes
    1.7-2.0 km apart (the frame above) and a car's route ran onto a cyclist-only synthesised
    lane (SUMO refused it); a motorcycle recorded as a cyclist departed faster than SUMO's
    bicycle allows. Both convert, with SUMO's run, and meet the route and on-network bars."""
    path = SHARED / "nuscenes_trainval" / f"sd_nuscenes_v1.0-trainval_{name}.pkl"
    if not path.is_file():
        pytest.skip("no shared nuScenes trainval data")
    rep = convert_scene(load_scenarionet(path), tmp_path)
    assert rep.status == "ok", rep.reason
    assert rep.quality["route_rate"] >= 0.95 and rep.quality["on_network_rate"] >= 0.98
