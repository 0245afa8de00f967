"""WOMD reader/writer on the real scenes, encodings and bad records."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from conftest import EXPECTED, WOMD_DIR
from converters import iter_scene_records, iter_scenes, load_scene
from converters.tfrecord import encode_record, iter_records
from converters.womd import iter_womd, parse_scenario, scene_to_proto, write_womd
from converters.womd.protos import scenario_pb2 as pb
from magail_sumo.scene import SceneValidationError
from wire import encode_varint, field_bytes, fields

MAP_ONEOF = {3: "lane", 4: "road_line", 5: "road_edge", 7: "stop_sign", 8: "crosswalk",
             9: "speed_bump", 10: "driveway"}


@pytest.mark.parametrize("scenario_id", sorted(EXPECTED))
def test_counts_equal_official_parse(scenario_id):
    scene = load_scene(WOMD_DIR / f"{scenario_id}.tfrecord")
    assert scene.summary() == EXPECTED[scenario_id]


def test_counts_agree_with_schema_free_decoder(real_scene_file):
    """Our schema-based reader and a bare wire decoder count the same things."""
    [(_, data)] = list(iter_records(real_scene_file))
    top = fields(data)
    scene = load_scene(real_scene_file)
    assert scene.tracks.num_tracks == len(top[2])
    kinds = {k: 0 for k in MAP_ONEOF.values()}
    for feat in top[8]:
        for num in fields(feat):
            if num in MAP_ONEOF:
                kinds[MAP_ONEOF[num]] += 1
    assert scene.roadmap.count_by_kind() == kinds
    valid = 0
    for track in top[2]:
        for state in fields(track)[3]:
            valid += fields(state).get(11, [0])[-1]
    assert int(scene.tracks.valid.sum()) == valid
    lane_states = sum(len(fields(d).get(1, [])) for d in top[7])
    assert len(scene.signals) == lane_states


def test_scene_arrays_hold_recorded_values(scene_637f):
    tr = scene_637f.tracks
    assert tr.x.dtype == np.float64 and tr.heading.dtype == np.float32
    assert tr.x.shape == (83, 91) and not tr.x.flags.writeable
    assert tr.valid[scene_637f.sdc_track_index, scene_637f.current_time_index]
    # recorded velocities agree with the finite differences of recorded positions (m/s)
    both = tr.valid[:, :-1] & tr.valid[:, 1:]
    dt = np.diff(scene_637f.timestamps)
    fd = np.hypot(np.diff(tr.x, axis=1), np.diff(tr.y, axis=1)) / dt
    speed = np.hypot(tr.vx, tr.vy)[:, :-1]
    moving = both & (speed > 5.0)
    assert moving.sum() > 100
    assert np.median(np.abs(speed[moving] - fd[moving])) < 0.3
    lane = scene_637f.roadmap.lanes[0]
    assert lane.polyline.shape[1] == 3 and lane.polyline.shape[0] > 1
    assert [r.difficulty for r in scene_637f.tracks_to_predict] == [1, 1, 2]
    assert scene_637f.signals.at_step(0).lane.tolist()[:3] == [431, 432, 443]


def test_write_read_round_trip_all_real_scenes(tmp_path, real_scene):
    path = tmp_path / "rt.tfrecord"
    write_womd(path, [real_scene])
    back = load_scene(path)
    assert back == real_scene, back.differences(real_scene)


def test_gzip_multi_scene_shard_is_read_lazily(tmp_path, real_scene_file):
    scenes = [load_scene(f) for f in sorted(WOMD_DIR.glob("*.tfrecord"))]
    path = tmp_path / "shard.tfrecord.gz"
    assert write_womd(path, scenes * 2) == 6
    it = iter_scenes(path)
    first = next(it)  # a generator: yields before the rest is read
    assert first == scenes[0]
    assert [s.scenario_id for s in it] == [s.scenario_id for s in scenes[1:] + scenes]


def test_packed_and_unpacked_repeated_fields(scene_637f):
    msg = scene_to_proto(scene_637f)
    ts = list(msg.timestamps_seconds)
    ooi = [3, 7]
    lane = msg.map_features[0]
    assert lane.HasField("lane")
    exits = list(lane.lane.exit_lanes)
    del msg.timestamps_seconds[:]
    base = msg.SerializeToString()
    packed_ts = field_bytes(1, struct.pack(f"<{len(ts)}d", *ts))
    unpacked_ts = b"".join(encode_varint(1 << 3 | 1) + struct.pack("<d", v) for v in ts)
    ids = {int(i) for i in scene_637f.tracks.id[:2]}
    ooi = sorted(ids)
    packed_ooi = field_bytes(4, b"".join(encode_varint(v) for v in ooi))
    unpacked_ooi = b"".join(encode_varint(4 << 3) + encode_varint(v) for v in ooi)
    for ts_enc, ooi_enc in ((packed_ts, unpacked_ooi), (unpacked_ts, packed_ooi)):
        scene = parse_scenario(base + ts_enc + ooi_enc)
        assert scene.timestamps.tolist() == ts
        assert list(scene.objects_of_interest) == ooi
    # exit_lanes is declared packed; an unpacked encoding parses the same
    assert exits, "first lane has exit lanes"
    center = pb.LaneCenter()
    center.CopyFrom(lane.lane)
    del center.exit_lanes[:]
    unpacked = center.SerializeToString() + b"".join(
        encode_varint(10 << 3) + encode_varint(v) for v in exits)
    assert list(pb.LaneCenter.FromString(unpacked).exit_lanes) == exits


def test_unknown_fields_are_skipped(scene_637f):
    msg = scene_to_proto(scene_637f)
    last = msg.tracks[-1].SerializeToString()
    del msg.tracks[-1]
    track = pb.Track.FromString(last)
    states = [s.SerializeToString() for s in track.states]
    states[0] += encode_varint(30 << 3) + encode_varint(5)  # unknown field inside an ObjectState
    del track.states[:]
    track_with_unknown = (track.SerializeToString() + b"".join(field_bytes(3, s) for s in states)
                          + encode_varint(99 << 3 | 2) + encode_varint(3) + b"abc")
    data = (msg.SerializeToString() + field_bytes(2, track_with_unknown)
            + field_bytes(12, b"lidar bytes") + field_bytes(13, b"camera tokens")
            + encode_varint(200 << 3) + encode_varint(1))
    assert parse_scenario(data) == scene_637f


@pytest.mark.parametrize("extra, field_name", [
    (encode_varint(5 << 3) + encode_varint(7), "scenario_id"),      # string sent as varint
    (encode_varint(2 << 3 | 5) + b"\0\0\0\0", "tracks"),             # message sent as fixed32
])
def test_wrong_typed_field_is_an_error(scene_637f, extra, field_name):
    data = scene_to_proto(scene_637f).SerializeToString() + extra
    with pytest.raises(SceneValidationError, match=f"field {field_name} .*wrong type"):
        parse_scenario(data)


def test_invalid_enum_value_in_nested_message_is_an_error(scene_637f):
    msg = scene_to_proto(scene_637f)
    last = msg.tracks[-1].SerializeToString()
    del msg.tracks[-1]
    bad_track = last + encode_varint(2 << 3) + encode_varint(9)  # object_type 9 does not exist
    with pytest.raises(SceneValidationError, match=r"tracks\[82\]\.object_type"):
        parse_scenario(msg.SerializeToString() + field_bytes(2, bad_track))


def _record_file(tmp_path, msg, name="bad.tfrecord"):
    path = tmp_path / name
    path.write_bytes(encode_record(msg.SerializeToString()))
    return path


def _bad_record_error(tmp_path, msg) -> str:
    [rec] = list(iter_scene_records(_record_file(tmp_path, msg)))
    assert not rec.ok and rec.index == 0
    text = str(rec.error)
    assert "\n" not in text and "bad.tfrecord: record 0:" in text
    return text


def test_zero_tracks(tmp_path, scene_637f):
    msg = scene_to_proto(scene_637f)
    del msg.tracks[:]
    msg.ClearField("sdc_track_index")
    del msg.tracks_to_predict[:]
    assert "zero tracks" in _bad_record_error(tmp_path, msg)


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_coordinates(tmp_path, scene_637f, value):
    msg = scene_to_proto(scene_637f)
    msg.tracks[5].states[40].center_y = value
    text = _bad_record_error(tmp_path, msg)
    assert f"track {msg.tracks[5].id} step 40: field y is {value}" in text
    msg = scene_to_proto(scene_637f)
    msg.map_features[3].lane.polyline[0].x = value
    assert f"lane {msg.map_features[3].id}: coordinates contain NaN or inf" in _bad_record_error(tmp_path, msg)


@pytest.mark.parametrize("kind", ["entry_lanes", "exit_lanes", "left_neighbors"])
def test_dangling_lane_reference(tmp_path, scene_637f, kind):
    msg = scene_to_proto(scene_637f)
    lane = next(f for f in msg.map_features if f.HasField("lane") and len(getattr(f.lane, kind)))
    if kind == "left_neighbors":
        lane.lane.left_neighbors[0].feature_id = 987654
    else:
        getattr(lane.lane, kind)[0] = 987654
    text = _bad_record_error(tmp_path, msg)
    assert f"lane {lane.id}: {kind[:-1]} 987654 does not exist" in text


def test_multi_scene_shard_with_corrupt_record_continues(tmp_path):
    datas = [d for f in sorted(WOMD_DIR.glob("*.tfrecord")) for _, d in iter_records(f)]
    corrupt = bytearray(encode_record(datas[1]))
    corrupt[500] ^= 0x40
    path = tmp_path / "shard.tfrecord"
    path.write_bytes(encode_record(datas[0]) + bytes(corrupt) + encode_record(datas[2]))
    recs = list(iter_womd(path))
    assert [type(s).__name__ for _, s in recs] == ["Scene", "SceneFormatError", "Scene"]
    assert "record 1: data CRC mismatch" in str(recs[1][1])


def test_fast_point_decoding_equals_per_point_decoding(real_scene_file):
    from converters.womd.reader import _point_lists, scene_from_proto
    [(_, data)] = list(iter_records(real_scene_file))
    msg = pb.Scenario.FromString(data)
    fast = _point_lists(data)
    assert sum(p is not None for p in fast) == len(msg.map_features)  # real data: all canonical
    assert scene_from_proto(msg, fast) == scene_from_proto(msg)


def test_non_canonical_points_fall_back(scene_637f):
    msg = scene_to_proto(scene_637f)
    lane = next(f for f in msg.map_features if f.HasField("lane"))
    lane.lane.polyline[0].ClearField("z")  # z absent: a 18-byte MapPoint
    lane.lane.polyline[1].z = 0.0
    scene = parse_scenario(msg.SerializeToString())
    got = scene.roadmap.lane(lane.id).polyline
    assert got[0, 2] == 0.0 and got[0, 0] == lane.lane.polyline[0].x
    assert np.array_equal(got[2:], scene_637f.roadmap.lane(lane.id).polyline[2:])


# ----------------------------------------------------------------- map points far outside the scene
def _record_error(tmp_path, msg) -> str:
    path = tmp_path / "bad.tfrecord"
    path.write_bytes(encode_record(msg.SerializeToString()))
    [rec] = list(iter_scene_records(path))
    assert not rec.ok and rec.index == 0
    text = str(rec.error)
    assert "\n" not in text and text.startswith(f"{path}: record 0: ")
    return text


@pytest.mark.parametrize("x", [1e9, 5e4])
def test_map_point_far_outside_the_scene_is_refused_naming_the_feature(tmp_path, scene_637f, x):
    """One lane point at x = 1e9 once drove ``convert`` past 7.9 GB; 50 km out is refused too."""
    msg = scene_to_proto(scene_637f)
    k = next(i for i, f in enumerate(msg.map_features) if f.HasField("lane"))
    msg.map_features[k].lane.polyline[1].x = x
    text = _record_error(tmp_path, msg)
    assert (f"lane {msg.map_features[k].id}: point ({x:.6g}, " in text
            and "is far outside the scene (more than 10000 m from the bounding box of the valid "
                "object states)" in text), text


def test_far_stop_sign_and_stop_point_are_refused(tmp_path, scene_637f):
    msg = scene_to_proto(scene_637f)
    k = next(i for i, f in enumerate(msg.map_features) if f.HasField("stop_sign"))
    msg.map_features[k].stop_sign.position.y = -3e6
    assert f"stop_sign {msg.map_features[k].id}: point (" in _record_error(tmp_path, msg)
    msg = scene_to_proto(scene_637f)
    ls = msg.dynamic_map_states[4].lane_states[0]
    ls.stop_point.x = 1e8
    assert (f"signal state of lane {ls.lane} at step 4: stop_point (1e+08, "
            in _record_error(tmp_path, msg))


def test_map_near_the_scene_is_kept(scene_637f):
    """Real maps reach ~150 m past the agents; a point 9 km out is still accepted."""
    from dataclasses import replace

    from magail_sumo.scene import validate_scene
    lane = scene_637f.roadmap.lanes[0]
    tr = scene_637f.tracks
    far = tr.x[tr.valid].max() + 9_000.0
    pts = np.array(lane.polyline)
    pts[0, 0] = far
    lanes = (replace(lane, polyline=pts),) + scene_637f.roadmap.lanes[1:]
    validate_scene(replace(scene_637f, roadmap=replace(scene_637f.roadmap, lanes=lanes)))


# ------------------------------------------------------------------------------- an unusable record
def test_unusable_womd_record_is_a_one_line_error_with_the_reason(tmp_path, scene_637f):
    msg = scene_to_proto(scene_637f)
    for track in msg.tracks:
        for s in track.states:
            s.center_x, s.center_y = 1e308, -1e308
    path = tmp_path / "far.tfrecord"
    path.write_bytes(encode_record(msg.SerializeToString()))
    [rec] = list(iter_scene_records(path))
    assert "field x is 1e+308, out of range" in str(rec.error)
