"""Evaluation windows (magail_sumo.scene.window) on the bundled real scenes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR
from converters import iter_scenes, load_scene
from converters.scenarionet import load_scenarionet, write_scenarionet
from magail_sumo.scene import (
    STATE_FIELDS, ObjectType, WindowError, choose_tracks_to_predict, window,
)

SN = ROOT / "data" / "scenarionet"


@pytest.fixture(scope="module")
def long_scene():
    """A 20 s WOMD scene with signals, current step 0 and no tracks to predict."""
    sc = load_scene(SN / "49c341dce1f65cdb.pkl")
    assert sc.num_steps == 198 and sc.current_time_index == 0 and not sc.tracks_to_predict
    assert len(sc.signals)
    return sc


def test_slicing_is_exact(long_scene):
    src, start = long_scene, 50
    w = window(src, start)
    steps = slice(start, start + 91)
    assert w.scenario_id == "49c341dce1f65cdb-w50"
    assert w.num_steps == 91 and w.current_time_index == 10
    keep = src.tracks.valid[:, steps].any(axis=1)
    assert 0 < keep.sum() < src.tracks.num_tracks  # some tracks lie outside this window
    np.testing.assert_array_equal(w.tracks.id, src.tracks.id[keep])
    np.testing.assert_array_equal(w.tracks.type, src.tracks.type[keep])
    for name in (*STATE_FIELDS, "valid"):
        np.testing.assert_array_equal(getattr(w.tracks, name),
                                      getattr(src.tracks, name)[keep][:, steps], err_msg=name)
    np.testing.assert_array_equal(w.timestamps, src.timestamps[steps] - src.timestamps[start])
    assert w.timestamps[0] == 0.0
    sel = (src.signals.step >= start) & (src.signals.step < start + 91)
    assert 0 < sel.sum() < len(src.signals)
    np.testing.assert_array_equal(w.signals.step, src.signals.step[sel] - start)
    for name in ("lane", "state", "stop_point"):
        np.testing.assert_array_equal(getattr(w.signals, name), getattr(src.signals, name)[sel])
    assert w.tracks.id[w.sdc_track_index] == src.tracks.id[src.sdc_track_index]
    assert w.roadmap == src.roadmap
    assert set(w.objects_of_interest) == set(src.objects_of_interest) & set(w.tracks.id.tolist())


def test_window_of_a_91_step_scene_keeps_its_tracks_to_predict():
    src = load_scene(WOMD_DIR / "637f20cafde22ff8.tfrecord")
    w = window(src, 0)
    assert w.scenario_id == "637f20cafde22ff8-w0" and w.tracks == src.tracks
    assert w.signals == src.signals and w.tracks_to_predict == src.tracks_to_predict
    assert len(w.tracks_to_predict) == 3


def _brute_force_candidates(sc, min_move=2.0):
    """The rule, written out track by track."""
    tr, c, sdc = sc.tracks, sc.current_time_index, sc.sdc_track_index
    out = []
    for i in range(tr.num_tracks):
        if i == sdc or tr.type[i] != ObjectType.VEHICLE or not tr.valid[i, c:].all():
            continue
        moved = max(np.hypot(tr.x[i, t] - tr.x[i, c], tr.y[i, t] - tr.y[i, c])
                    for t in range(c, sc.num_steps))
        if moved >= min_move:
            out.append((float(np.hypot(tr.x[i, c] - tr.x[sdc, c], tr.y[i, c] - tr.y[sdc, c])), i))
    return [i for _, i in sorted(out)]


@pytest.mark.parametrize("start", [0, 50, 100])
def test_tracks_to_predict_rule(long_scene, start):
    w = window(long_scene, start)
    chosen = [r.track_index for r in w.tracks_to_predict]
    assert chosen == _brute_force_candidates(w)[:8]
    assert 1 <= len(chosen) <= 8 and w.sdc_track_index not in chosen


def test_tracks_to_predict_rule_constructed(long_scene):
    w = window(long_scene, 0)
    first = [r.track_index for r in w.tracks_to_predict]
    assert len(first) >= 3
    assert [r.track_index for r in choose_tracks_to_predict(w, max_tracks=2)] == first[:2]
    # park the nearest chosen vehicle at its current position: no longer a candidate
    i, c = first[0], w.current_time_index
    x, y = w.tracks.x.copy(), w.tracks.y.copy()
    x[i, c:], y[i, c:] = x[i, c], y[i, c] + np.linspace(0, 1.9, w.num_steps - c)  # 1.9 m
    parked = dataclasses.replace(w, tracks=dataclasses.replace(w.tracks, x=x, y=y))
    assert [r.track_index for r in choose_tracks_to_predict(parked)] == first[1:] + \
        [j for j in _brute_force_candidates(parked) if j not in first][:1]
    # a vehicle losing validity after the current step is not a candidate
    valid = w.tracks.valid.copy()
    valid[first[1], -1] = False
    gap = dataclasses.replace(w, tracks=dataclasses.replace(w.tracks, valid=valid))
    assert first[1] not in [r.track_index for r in choose_tracks_to_predict(gap)]


def test_window_errors(long_scene):
    with pytest.raises(WindowError, match=r"49c341dce1f65cdb: window start 108 \+ length 91 "
                                          r"does not fit its 198 steps \(start must be in 0\.\.107\)"):
        window(long_scene, 108)
    with pytest.raises(WindowError, match="start -1"):
        window(long_scene, -1)
    with pytest.raises(WindowError, match="current step 91"):
        window(long_scene, 0, current=91)
    valid = long_scene.tracks.valid.copy()
    valid[long_scene.sdc_track_index, 60] = False
    bad = dataclasses.replace(long_scene, tracks=dataclasses.replace(long_scene.tracks,
                                                                     valid=valid))
    with pytest.raises(WindowError, match=r"window start 50: the SDC .* not valid at its "
                                          r"current step \(source step 60\)"):
        window(bad, 50)
    assert window(bad, 51).num_steps == 91


@pytest.mark.parametrize("name,start", [("49c341dce1f65cdb", 50), ("8799c31b5be1f312", 0),
                                        ("2a1e44d405a6833f", 0)])
def test_round_trip_through_the_scenarionet_writer(tmp_path, name, start):
    w = window(load_scene(SN / f"{name}.pkl"), start)
    path = write_scenarionet(tmp_path / f"{w.scenario_id}.pkl", w)
    back = load_scenarionet(path)
    assert back == w, w.differences(back)
    # what magail-sumo evaluate reads
    (again,) = list(iter_scenes(path))
    assert again == w and again.current_time_index == 10 and again.tracks_to_predict
