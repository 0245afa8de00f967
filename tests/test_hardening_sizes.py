"""Sizes claimed by a file never become allocations: TFRecord lengths, gzip bombs, map extents.

Memory is measured with ``tracemalloc`` (it records an allocation's full size even when its
pages are never touched), so a regression that allocates a claimed length is caught without
the machine actually spending gigabytes.
"""

from __future__ import annotations

import gzip
import struct
import tracemalloc

import numpy as np
import pytest

from conftest import WOMD_DIR
from converters import iter_scene_records
from converters.tfrecord import (
    GZIP_MIN_RECORD_BUDGET, encode_record, iter_records, masked_crc32c, write_records,
)
from converters.womd import scene_to_proto

MiB = 1 << 20


def _header(length: int) -> bytes:
    head = struct.pack("<Q", length)
    return head + struct.pack("<I", masked_crc32c(head))


def _peak(fn):
    tracemalloc.start()
    try:
        result = fn()
        return result, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_28_byte_file_claiming_2gib_is_truncated_without_allocating(tmp_path):
    path = tmp_path / "claim.tfrecord"
    path.write_bytes(_header(2**31) + b"x" * 16)
    assert path.stat().st_size == 28
    recs, peak = _peak(lambda: list(iter_records(path)))
    [(index, err)] = recs
    assert index == 0 and err.fatal_for_file
    assert str(err) == (f"{path}: record 0: truncated record: length field 2147483648 but only "
                        "16 bytes left in the file")
    assert peak < 16 * MiB


def test_gzip_record_is_read_in_pieces(tmp_path):
    """A gzip record claiming 200 MiB (inside the budget) with 1 kB present costs ~chunk size."""
    path = tmp_path / "claim.tfrecord.gz"
    path.write_bytes(gzip.compress(_header(200 * MiB) + b"x" * 1000))
    recs, peak = _peak(lambda: list(iter_records(path)))
    [(_, err)] = recs
    assert "record 0: truncated record: 1000 of 209715204 bytes present" in str(err)
    assert peak < 32 * MiB


def test_gzip_bomb_is_refused_before_decompressing(tmp_path):
    path = tmp_path / "bomb.tfrecord.gz"
    path.write_bytes(gzip.compress(_header(GZIP_MIN_RECORD_BUDGET + 1) + b"\0" * 1000))
    recs, peak = _peak(lambda: list(iter_records(path)))
    [(_, err)] = recs
    assert err.fatal_for_file and "\n" not in str(err)
    assert (f"record 0: record length {GZIP_MIN_RECORD_BUDGET + 1} exceeds the decompression "
            f"limit of {GZIP_MIN_RECORD_BUDGET} bytes") in str(err)
    assert peak < 16 * MiB


def test_real_records_still_read_plain_and_gzip(tmp_path):
    records = [d for _, d in iter_records(WOMD_DIR / "850c48d8bbfa008f.tfrecord")]
    for name in ("x.tfrecord", "x.tfrecord.gz"):
        write_records(tmp_path / name, records * 2)
        back = [d for _, d in iter_records(tmp_path / name)]
        assert back == records * 2


def test_second_record_truncated_names_its_index(tmp_path):
    good = encode_record(b"hello")
    path = tmp_path / "two.tfrecord"
    path.write_bytes(good + _header(10**9) + b"abc")
    recs = list(iter_records(path))
    assert recs[0] == (0, b"hello")
    assert "record 1: truncated record: length field 1000000000 but only 3 bytes left" \
        in str(recs[1][1])


# ------------------------------------------------------------------ map coordinates

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


# ------------------------------------------------------------------ shared pickle objects

def _state(steps: int) -> dict:
    ones = np.ones(steps, bool)
    return {"position": np.zeros((steps, 2), bool), "heading": ones, "valid": ones,
            "length": ones, "width": ones, "height": ones}


def _load_peak(path):
    from converters.scenarionet import load_scenarionet
    from magail_sumo.errors import SceneFormatError

    def run():
        with pytest.raises(SceneFormatError) as err:
            load_scenarionet(path)
        return str(err.value)
    return _peak(run)


def test_tracks_sharing_one_state_cannot_blow_up(tmp_path):
    """5000 tracks referencing one 20000-step state: a 300 kB pickle describing a 6 GB scene."""
    import pickle

    state = _state(20_000)
    sd = {"id": "x", "length": 20_000, "map_features": {}, "dynamic_map_states": {},
          "metadata": {"ts": np.arange(20_000, dtype=np.int32), "scenario_id": "x"},
          "tracks": {str(i): {"type": "VEHICLE", "state": state} for i in range(5000)}}
    path = tmp_path / "shared.pkl"
    path.write_bytes(pickle.dumps(sd, protocol=4))
    assert path.stat().st_size < 400_000
    text, peak = _load_peak(path)
    assert text.startswith(f"{path}: record 0: tracks: the scene would take more than 67108864 "
                           "bytes of memory"), text
    assert peak < 64 * MiB


def test_map_features_sharing_one_polyline_cannot_blow_up(tmp_path):
    import pickle

    poly = np.zeros((100_000, 2), bool)
    sd = {"id": "x", "length": 2, "dynamic_map_states": {},
          "metadata": {"ts": np.arange(2.0), "scenario_id": "x"},
          "tracks": {"1": {"type": "VEHICLE", "state": _state(2)}},
          "map_features": {str(i): {"type": "ROAD_EDGE_BOUNDARY", "polyline": poly}
                           for i in range(10, 20_000)}}
    path = tmp_path / "shared_map.pkl"
    path.write_bytes(pickle.dumps(sd, protocol=4))
    text, peak = _load_peak(path)
    assert "].polyline: the scene would take more than 67108864 bytes" in text, text
    assert peak < 128 * MiB
