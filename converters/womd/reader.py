"""Read Waymo Open Motion Dataset ``Scenario`` records into :class:`~magail_sumo.scene.Scene`.

No TensorFlow: records are framed by :mod:`converters.tfrecord` and decoded with our own
protobuf schema (``protos/scenario.proto``). Unknown fields (lidar, camera tokens, future
additions) are skipped; a known field with the wrong wire type or an out-of-range enum value
is an error, never silently dropped.
"""

from __future__ import annotations

from os import PathLike
from typing import Iterator

import numpy as np
from google.protobuf.message import DecodeError
from google.protobuf.unknown_fields import UnknownFieldSet

from converters.tfrecord import iter_records
from converters.womd.protos import scenario_pb2 as pb
from magail_sumo.errors import SceneFormatError
from magail_sumo.scene import (
    STATE_FIELDS, BoundarySegment, Crosswalk, Driveway, Lane, LaneNeighbor, RequiredPrediction, RoadEdge,
    RoadLine, RoadMap, Scene, SceneValidationError, SignalStates, SpeedBump, StopSign, Tracks,
    validate_scene,
)

_WIRE_NAMES = {0: "varint", 1: "fixed64", 2: "length-delimited", 3: "group", 4: "group", 5: "fixed32"}


def parse_scenario(data: bytes) -> Scene:
    """Decode one serialized ``Scenario`` and validate it.

    :raises SceneValidationError: malformed protobuf, wrong-typed field or invalid scene.
    """
    try:
        msg = pb.Scenario.FromString(data)
    except DecodeError as exc:
        raise SceneValidationError(f"not a Scenario protobuf ({exc})") from None
    _check_unknown_fields(msg, len(data))
    scene = scene_from_proto(msg, _point_lists(data))
    validate_scene(scene)
    return scene


def iter_womd(path: str | PathLike) -> Iterator[tuple[int, Scene | SceneFormatError]]:
    """Yield ``(record_index, Scene or SceneFormatError)`` for every record of a TFRecord file.

    Lazy: memory is bounded by one record. A bad record yields its error and reading goes on
    when the framing allows it (see :func:`converters.tfrecord.iter_records`).
    """
    for index, data in iter_records(path):
        if isinstance(data, SceneFormatError):
            yield index, data
            continue
        try:
            yield index, parse_record(path, index, data)
        except SceneFormatError as exc:
            yield index, exc


def parse_record(path: str | PathLike, index: int, data: bytes) -> Scene:
    """:func:`parse_scenario` of record ``index`` of ``path``; any problem is a
    :class:`SceneFormatError` naming the file and record."""
    try:
        return parse_scenario(data)
    except SceneValidationError as exc:
        raise SceneFormatError(path, index, str(exc)) from None
    except (ValueError, OverflowError, RecursionError, MemoryError) as exc:  # unforeseen
        raise SceneFormatError(path, index, f"unexpected record structure "
                                            f"({type(exc).__name__}: {exc})") from None


# ------------------------------------------------------------------ wrong-typed fields

def _check_unknown_fields(msg: pb.Scenario, size: int) -> None:
    """Refuse known fields that protobuf set aside as unknown (wrong wire type / bad enum).

    Fast path: when dropping every unknown field leaves a message of the record's size, there
    were none. Otherwise walk a fresh copy and classify each unknown field.
    """
    probe = pb.Scenario()
    probe.CopyFrom(msg)
    probe.DiscardUnknownFields()
    if probe.ByteSize() == size:
        return
    _walk_unknown(msg, "")


def _walk_unknown(msg, path: str) -> None:
    desc = msg.DESCRIPTOR
    for unknown in UnknownFieldSet(msg):
        field = desc.fields_by_number.get(unknown.field_number)
        if field is not None:
            wire = _WIRE_NAMES.get(unknown.wire_type, str(unknown.wire_type))
            raise SceneValidationError(
                f"field {path}{field.name} (#{field.number}) has a wrong type or invalid value "
                f"(wire type {wire})"
            )
    for field, value in msg.ListFields():
        if field.message_type is None:
            continue
        if field.is_repeated:
            for i, item in enumerate(value):
                _walk_unknown(item, f"{path}{field.name}[{i}].")
        else:
            _walk_unknown(value, f"{path}{field.name}.")


# ------------------------------------------------------------------ proto -> Scene

def scene_from_proto(msg: pb.Scenario, points: list[np.ndarray | None] | None = None) -> Scene:
    """Convert a decoded ``Scenario`` message (no validation beyond shapes).

    :param points: per map feature, its decoded polyline/polygon (from :func:`_point_lists`);
        None entries (or no list) are decoded from ``msg``.
    """
    timestamps = np.asarray(msg.timestamps_seconds, np.float64)
    tracks = _tracks(msg, timestamps.shape[0])
    return Scene(
        scenario_id=msg.scenario_id,
        timestamps=timestamps,
        tracks=tracks,
        roadmap=_roadmap(msg.map_features, points),
        signals=_signals(msg.dynamic_map_states),
        sdc_track_index=msg.sdc_track_index if msg.HasField("sdc_track_index") else -1,
        current_time_index=msg.current_time_index,
        tracks_to_predict=tuple(
            RequiredPrediction(r.track_index, r.difficulty) for r in msg.tracks_to_predict
        ),
        objects_of_interest=tuple(msg.objects_of_interest),
    )


def _tracks(msg: pb.Scenario, num_steps: int) -> Tracks:
    n = len(msg.tracks)
    table = np.empty((n, num_steps, 10), np.float64)  # ObjectState fields in STATE_FIELDS order
    ids = np.empty(n, np.int64)
    types = np.empty(n, np.int8)
    for i, track in enumerate(msg.tracks):
        states = track.states
        if len(states) != num_steps:
            raise SceneValidationError(
                f"track {track.id} has {len(states)} states but the scene has {num_steps} timestamps"
            )
        ids[i] = track.id
        types[i] = track.object_type
        if num_steps:  # one pass over the states: each access builds a wrapper object
            table[i] = [(s.center_x, s.center_y, s.center_z, s.length, s.width, s.height, s.heading,
                         s.velocity_x, s.velocity_y, s.valid) for s in states]
    cols = {name: table[..., k] for k, name in enumerate(STATE_FIELDS)}
    return Tracks(id=ids, type=types, valid=table[..., 9] != 0, **cols)


_POINT_DTYPE = np.dtype([("tx", "u1"), ("x", "<f8"), ("ty", "u1"), ("y", "<f8"),
                         ("tz", "u1"), ("z", "<f8")])
_POINT_TAGS = (0x09, 0x11, 0x19)  # fields 1, 2, 3 as fixed64
_VIEW_FIELD = {"lane": "field_8", "road_line": "field_2", "road_edge": "field_2",
               "crosswalk": "field_1", "speed_bump": "field_1", "driveway": "field_1"}


def _point_lists(data: bytes) -> list[np.ndarray | None]:
    """Decode every map feature's points straight from the wire bytes (None: use the slow path).

    Works when each MapPoint is canonically encoded with x, y and z (27 bytes); anything else
    falls back to per-point decoding for that feature.
    """
    view = pb.ScenarioMapView.FromString(data)
    out: list[np.ndarray | None] = []
    for feat in view.map_features:
        kind = _view_kind(feat)
        raw = getattr(getattr(feat, kind), _VIEW_FIELD[kind]) if kind else ()
        if kind and raw and all(len(r) == 27 for r in raw):
            rec = np.frombuffer(b"".join(raw), _POINT_DTYPE)
            if ((rec["tx"] == _POINT_TAGS[0]) & (rec["ty"] == _POINT_TAGS[1])
                    & (rec["tz"] == _POINT_TAGS[2])).all():
                out.append(np.stack([rec["x"], rec["y"], rec["z"]], axis=1))
                continue
        out.append(None if kind and raw else np.zeros((0, 3)))
    return out


def _view_kind(feat) -> str | None:
    for kind in _VIEW_FIELD:
        if feat.HasField(kind):
            return kind
    return None


def _points(points) -> np.ndarray:
    flat = [c for p in points for c in (p.x, p.y, p.z)]
    return np.array(flat, np.float64).reshape(-1, 3)


def _segments(segs) -> tuple[BoundarySegment, ...]:
    return tuple(
        BoundarySegment(s.lane_start_index, s.lane_end_index, s.boundary_feature_id, s.boundary_type)
        for s in segs
    )


def _neighbors(nbs) -> tuple[LaneNeighbor, ...]:
    return tuple(
        LaneNeighbor(n.feature_id, n.self_start_index, n.self_end_index, n.neighbor_start_index,
                     n.neighbor_end_index, _segments(n.boundaries))
        for n in nbs
    )


def _roadmap(features, point_lists: list[np.ndarray | None] | None = None) -> RoadMap:
    kinds: dict[str, list] = {k: [] for k in
                              ("lane", "road_line", "road_edge", "stop_sign", "crosswalk",
                               "speed_bump", "driveway")}
    decoded = point_lists if point_lists is not None else [None] * len(features)

    def pts(i: int, field) -> np.ndarray:
        fast = decoded[i]
        return fast if fast is not None else _points(field)

    for i, f in enumerate(features):
        kind = f.WhichOneof("feature_data")
        if kind is None:
            raise SceneValidationError(f"map feature {f.id} has no feature data")
        if kind == "lane":
            ln = f.lane
            kinds[kind].append(Lane(
                id=f.id, polyline=pts(i, ln.polyline), type=ln.type,
                speed_limit_mph=ln.speed_limit_mph, interpolating=ln.interpolating,
                entry_lanes=tuple(ln.entry_lanes), exit_lanes=tuple(ln.exit_lanes),
                left_neighbors=_neighbors(ln.left_neighbors),
                right_neighbors=_neighbors(ln.right_neighbors),
                left_boundaries=_segments(ln.left_boundaries),
                right_boundaries=_segments(ln.right_boundaries),
            ))
        elif kind == "road_line":
            kinds[kind].append(RoadLine(f.id, pts(i, f.road_line.polyline), f.road_line.type))
        elif kind == "road_edge":
            kinds[kind].append(RoadEdge(f.id, pts(i, f.road_edge.polyline), f.road_edge.type))
        elif kind == "stop_sign":
            p = f.stop_sign.position
            kinds[kind].append(StopSign(f.id, tuple(f.stop_sign.lane), (p.x, p.y, p.z)))
        elif kind == "crosswalk":
            kinds[kind].append(Crosswalk(f.id, pts(i, f.crosswalk.polygon)))
        elif kind == "speed_bump":
            kinds[kind].append(SpeedBump(f.id, pts(i, f.speed_bump.polygon)))
        else:
            kinds[kind].append(Driveway(f.id, pts(i, f.driveway.polygon)))
    return RoadMap(**{k + "s": tuple(v) for k, v in kinds.items()})


def _signals(dynamic_states) -> SignalStates:
    steps, lanes, states, points = [], [], [], []
    for t, dyn in enumerate(dynamic_states):
        for ls in dyn.lane_states:
            steps.append(t)
            lanes.append(ls.lane)
            states.append(ls.state)
            p = ls.stop_point
            points.append((p.x, p.y, p.z))
    if not steps:
        return SignalStates.empty()
    return SignalStates(np.array(steps), np.array(lanes), np.array(states), np.array(points))
