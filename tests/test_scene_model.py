"""The Scene dataclasses: immutability, value equality, shape checks, validation rules."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from magail_sumo.scene import (
    Lane, ObjectType, RoadMap, Scene, SceneValidationError, SignalStates, Tracks, validate_scene,
)


def test_scene_is_frozen_and_arrays_read_only(scene_637f):
    with pytest.raises(dataclasses.FrozenInstanceError):
        scene_637f.scenario_id = "x"  # type: ignore[misc]
    with pytest.raises(ValueError):
        scene_637f.tracks.x[0, 0] = 1.0
    assert not scene_637f.roadmap.lanes[0].polyline.flags.writeable


def test_value_equality_and_differences(scene_637f):
    tr = scene_637f.tracks
    fields = {f.name: getattr(tr, f.name) for f in dataclasses.fields(tr)}
    x = np.array(tr.x)
    x[3, 4] += 0.001
    changed = dataclasses.replace(scene_637f, tracks=Tracks(**{**fields, "x": x}))
    same = dataclasses.replace(scene_637f, tracks=Tracks(**fields))
    assert same == scene_637f and changed != scene_637f
    assert changed.differences(scene_637f) == ["tracks.x"]


def test_shape_mismatch_is_refused():
    with pytest.raises(ValueError, match="Tracks: expected shape"):
        Tracks(id=[1, 2], type=[1], x=np.zeros((2, 3)), y=np.zeros((2, 3)), z=np.zeros((2, 3)),
               length=np.zeros((2, 3)), width=np.zeros((2, 3)), height=np.zeros((2, 3)),
               heading=np.zeros((2, 3)), vx=np.zeros((2, 3)), vy=np.zeros((2, 3)),
               valid=np.zeros((2, 3), bool))
    with pytest.raises(ValueError, match="timestamps"):
        Scene("s", np.zeros(4), Tracks.empty(3))
    with pytest.raises(ValueError, match="ordered by step"):
        SignalStates([2, 1], [5, 5], [4, 4], np.zeros((2, 3)))


def test_lookup_and_units(scene_637f):
    rm = scene_637f.roadmap
    lane = rm.lanes[0]
    assert rm.lane(lane.id) is lane
    assert lane.speed_limit == pytest.approx(lane.speed_limit_mph * 0.44704)
    with pytest.raises(KeyError):
        rm.lane(rm.road_edges[0].id)
    assert scene_637f.tracks.count_by_type()["vehicle"] == 70
    assert ObjectType(scene_637f.tracks.type[scene_637f.sdc_track_index]) is ObjectType.VEHICLE
    step0 = scene_637f.signals.at_step(0)
    assert len(step0) == 12 and set(step0.step.tolist()) == {0}


def _with_map(scene, **kinds):
    return dataclasses.replace(scene, roadmap=dataclasses.replace(scene.roadmap, **kinds))


def test_validation_rules(scene_637f):
    validate_scene(scene_637f)
    lanes = scene_637f.roadmap.lanes
    dup = _with_map(scene_637f, lanes=lanes + (Lane(lanes[0].id, lanes[0].polyline),))
    with pytest.raises(SceneValidationError, match=f"duplicate map feature id {lanes[0].id}"):
        validate_scene(dup)
    with pytest.raises(SceneValidationError, match="sdc_track_index 500 out of range"):
        validate_scene(dataclasses.replace(scene_637f, sdc_track_index=500))
    with pytest.raises(SceneValidationError, match="objects_of_interest id -7"):
        validate_scene(dataclasses.replace(scene_637f, objects_of_interest=(-7,)))
    empty = dataclasses.replace(scene_637f, tracks=Tracks.empty(91), sdc_track_index=-1,
                                tracks_to_predict=())
    with pytest.raises(SceneValidationError, match="zero tracks"):
        validate_scene(empty)
    assert RoadMap().count_by_kind()["lane"] == 0


# -------------------------------------------------- scenes with nothing usable, out-of-range values
def _tracks(scene, **cols) -> Tracks:
    tr = scene.tracks
    fields = {f.name: getattr(tr, f.name) for f in dataclasses.fields(tr)}
    fields.update(cols)
    return Tracks(**fields)


def _refused(scene, match: str) -> str:
    with pytest.raises(SceneValidationError) as err:
        validate_scene(scene)
    assert match in str(err.value), str(err.value)
    return str(err.value)


def test_huge_but_finite_coordinates_are_out_of_range(scene_637f):
    tr = scene_637f.tracks
    x = np.full(tr.x.shape, 1e308)
    y = np.full(tr.y.shape, -1e308)
    text = _refused(dataclasses.replace(scene_637f, tracks=_tracks(scene_637f, x=x, y=y)),
                    "field x is 1e+308, out of range (|x| > 1e+07 m)")
    assert "non-finite" not in text and "not finite" not in text
    x = np.array(tr.x)
    x[3, 5] = np.inf
    _refused(dataclasses.replace(scene_637f, tracks=_tracks(scene_637f, x=x)),
             f"track {int(tr.id[3])} step 5: field x is inf, not finite")


@pytest.mark.parametrize("kind", ["zero", "reversed", "repeated"])
def test_timestamps_must_increase(scene_637f, kind):
    ts = np.array(scene_637f.timestamps)
    if kind == "zero":
        ts[:] = 0.0
    elif kind == "reversed":
        ts = ts[::-1].copy()
    else:
        ts[40] = ts[39]
    _refused(dataclasses.replace(scene_637f, timestamps=ts),
             "timestamps not strictly increasing: step ")


def test_zero_steps_and_no_valid_state_are_refused(scene_637f):
    cols = {f.name: getattr(scene_637f.tracks, f.name)[:, :0] for f in dataclasses.fields(Tracks)
            if f.name not in ("id", "type")}
    empty = dataclasses.replace(scene_637f, timestamps=np.zeros(0),
                                tracks=_tracks(scene_637f, **cols))
    _refused(empty, "scene has zero time steps")
    invalid = np.zeros(scene_637f.tracks.valid.shape, bool)
    _refused(dataclasses.replace(scene_637f, tracks=_tracks(scene_637f, valid=invalid)),
             "no track has a valid state")


@pytest.mark.parametrize("name, value, rule", [("length", 0.0, "positive"),
                                               ("width", -1.0, "positive"),
                                               ("height", -0.5, "non-negative")])
def test_box_sizes_on_valid_states(scene_637f, name, value, rule):
    tr = scene_637f.tracks
    i, t = (int(v[0]) for v in np.nonzero(tr.valid))
    arr = np.array(getattr(tr, name))
    arr[i, t] = value
    _refused(dataclasses.replace(scene_637f, tracks=_tracks(scene_637f, **{name: arr})),
             f"track {int(tr.id[i])} step {t}: box {name} {value:g} on a valid state "
             f"(must be {rule})")
    # the same value on an invalid state carries no meaning and is kept
    j, s = (int(v[0]) for v in np.nonzero(~tr.valid))
    arr = np.array(getattr(tr, name))
    arr[j, s] = value
    validate_scene(dataclasses.replace(scene_637f, tracks=_tracks(scene_637f, **{name: arr})))


def test_real_scenes_still_valid(real_scene):
    validate_scene(real_scene)


def test_boundary_message_spelling(scene_637f):
    lane = next(ln for ln in scene_637f.roadmap.lanes if ln.right_boundaries)
    seg = dataclasses.replace(lane.right_boundaries[0], boundary_feature_id=987654321)
    bad = dataclasses.replace(lane, right_boundaries=(seg,) + lane.right_boundaries[1:])
    lanes = tuple(bad if ln is lane else ln for ln in scene_637f.roadmap.lanes)
    text = _refused(dataclasses.replace(scene_637f, roadmap=dataclasses.replace(
        scene_637f.roadmap, lanes=lanes)), f"lane {lane.id}: right_boundary feature 987654321")
    assert "boundariy" not in text
