"""GPUDrive / Nocturne JSON scenes: the format in which the GPUDrive and PufferDrive community
circulates thousands of WOMD scenes (one scene per ``.json`` file).

Layout (GPUDrive's ``waymo_data_processing``; Nocturne's and PufferDrive's differ in the
details this reader accepts too)::

    {"name": file name, "scenario_id": WOMD id,
     "objects": [{"id": int, "type": "vehicle" | "pedestrian" | "cyclist" | ...,
                  "position": [{"x", "y", "z"?}] x T, "heading": [rad] x T,
                  "velocity": [{"x", "y"}] x T, "valid": [bool] x T,
                  "length", "width", "height": m, "goalPosition", "mark_as_expert"}],
     "roads": [{"id": int, "type": "lane" | "road_line" | "road_edge" | "stop_sign" |
                "crosswalk" | "speed_bump" | "driveway", "map_element_id": int,
                "geometry": [{"x", "y", "z"?}]}],
     "tl_states": {...}, "metadata": {"sdc_track_index", "tracks_to_predict":
                  [{"track_index", "difficulty"}], "objects_of_interest": [ids]}}

* Points may also be ``[x, y]`` / ``[x, y, z]`` lists; a missing ``z`` is 0; a missing
  ``velocity`` is derived from the positions (central differences of the valid steps); a
  missing ``height`` is 0.
* ``map_element_id`` is GPUDrive's ``MapElementIds``: WOMD's map types in one range (lane
  types 0-3, road lines 5-13 = WOMD road-line type + 5, road edges 14-16 = WOMD road-edge
  type + 14, stop sign 17, crosswalk 18, speed bump 19, driveway 20).
* The format has no lane connectivity: successors and neighbours are inferred from the lane
  geometry (:func:`~magail_sumo.scene.infer_lane_connectivity`, reported in
  ``Scene.data_quality``), as for ScenarioNet sources without links. Stop signs name no lanes.
* Signal states (``tl_states``) are read when they are per-lane state series
  (``{lane_id: {"state": [...] x T, "x": [...], "y": [...]}}``, WOMD state names or numbers,
  ``null`` where the lane has no record at that step); any other layout is dropped with a note.
* 10 Hz; the current step is ``metadata.current_time_index`` when given, else 10 (WOMD's).

Every problem is a :class:`~magail_sumo.errors.SceneFormatError` naming the file and the
field (``objects[3].position[17]``); files are read through :mod:`magail_sumo.inputs`
(regular files only, at most 512 MiB, JSON nested at most 16 deep).
"""

from __future__ import annotations

import dataclasses
from os import PathLike
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from magail_sumo.errors import SceneFormatError
from magail_sumo.inputs import MiB, InputFileError, read_json
from magail_sumo.outputs import printable
from magail_sumo.scene import (
    Crosswalk, DataQuality, Driveway, Lane, LaneType, ObjectType, RequiredPrediction, RoadEdge,
    RoadEdgeType, RoadLine, RoadLineType, RoadMap, Scene, SceneValidationError, SignalState,
    SignalStates, SpeedBump, StopSign, Tracks, infer_lane_connectivity, validate_scene,
)
from magail_sumo.scene.connectivity import MAX_LANES as MAX_INFERRED_LANES

#: the largest file read (the biggest circulating scenes are tens of MB)
FILE_LIMIT = 512 * MiB
#: JSON nesting of the format: scene > list > object > list > point
MAX_DEPTH = 16
STEP = 0.1
WOMD_CURRENT_INDEX = 10
OBJECT_TYPES = {"vehicle": ObjectType.VEHICLE, "pedestrian": ObjectType.PEDESTRIAN,
                "cyclist": ObjectType.CYCLIST, "bicycle": ObjectType.CYCLIST,
                "other": ObjectType.OTHER, "unset": ObjectType.UNSET}
#: GPUDrive MapElementIds ranges (module doc)
ROAD_LINE_OFFSET, ROAD_EDGE_OFFSET = 5, 14
_STATE_NAMES = {s.name: s for s in SignalState}


class _Bad(Exception):
    """A field problem: the message names the field."""


def _num(v: Any, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _Bad(f"{where}: expected a number, got {type(v).__name__}")
    return float(v)


def _int(v: Any, where: str) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or int(v) != v:
        raise _Bad(f"{where}: expected an integer, got {printable(repr(v), 40)}")
    return int(v)


def _list(v: Any, where: str) -> list:
    if not isinstance(v, list):
        raise _Bad(f"{where}: expected a list, got {type(v).__name__}")
    return v


def _dict(v: Any, where: str) -> dict:
    if not isinstance(v, dict):
        raise _Bad(f"{where}: expected an object, got {type(v).__name__}")
    return v


def _points(v: Any, where: str, dims: int = 3) -> np.ndarray:
    """(P, dims) float64 from ``[{"x","y","z"?}]`` or ``[[x, y(, z)]]`` (missing z: 0)."""
    pts = _list(v, where)
    out = np.zeros((len(pts), dims))
    for k, p in enumerate(pts):
        if isinstance(p, dict):
            vals = [p.get("x"), p.get("y"), p.get("z", 0.0)][:dims]
        elif isinstance(p, list) and len(p) >= 2:
            vals = (list(p) + [0.0])[:dims]
        else:
            raise _Bad(f"{where}[{k}]: expected a point {{x, y}} or [x, y]")
        for d, x in enumerate(vals):
            out[k, d] = _num(x, f"{where}[{k}].{'xyz'[d]}")
    return out


def _velocity_from_positions(xy: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(T, 2) velocity from positions: central differences over valid neighbours, one-sided at
    the ends of a valid run, zero where no neighbour is valid."""
    t = xy.shape[0]
    v = np.zeros((t, 2))
    for k in np.flatnonzero(valid):
        prev = k - 1 if k > 0 and valid[k - 1] else k
        nxt = k + 1 if k + 1 < t and valid[k + 1] else k
        if nxt > prev:
            v[k] = (xy[nxt] - xy[prev]) / ((nxt - prev) * STEP)
    return v


def _tracks(objects: list, notes: list[str]) -> tuple[Tracks, int]:
    if not objects:
        raise _Bad("objects: the scene has no objects")
    first = _dict(objects[0], "objects[0]")
    t = len(_list(first.get("position"), "objects[0].position"))
    if t < 2:
        raise _Bad(f"objects[0].position: {t} steps, expected at least 2")
    n = len(objects)
    ids = np.zeros(n, np.int64)
    types = np.zeros(n, np.int8)
    xyz = np.zeros((n, t, 3))
    heading = np.zeros((n, t))
    vel = np.zeros((n, t, 2))
    valid = np.zeros((n, t), bool)
    size = np.zeros((n, 3))
    derived = 0
    for i, raw in enumerate(objects):
        w = f"objects[{i}]"
        o = _dict(raw, w)
        ids[i] = _int(o.get("id", i), f"{w}.id")
        kind = o.get("type", "other")
        if isinstance(kind, str):
            types[i] = OBJECT_TYPES.get(kind.lower(), ObjectType.OTHER)
        else:
            types[i] = ObjectType(_int(kind, f"{w}.type")) if _int(kind, f"{w}.type") in \
                set(ObjectType) else ObjectType.OTHER
        pos = _points(o.get("position"), f"{w}.position")
        if pos.shape[0] != t:
            raise _Bad(f"{w}.position: {pos.shape[0]} steps, the scene has {t}")
        xyz[i] = pos
        hd = _list(o.get("heading"), f"{w}.heading")
        vd = _list(o.get("valid"), f"{w}.valid")
        if len(hd) != t or len(vd) != t:
            raise _Bad(f"{w}: heading / valid have {len(hd)} / {len(vd)} steps, the scene {t}")
        heading[i] = [_num(h, f"{w}.heading[{k}]") for k, h in enumerate(hd)]
        valid[i] = [bool(x) for x in vd]
        if o.get("velocity") is None:
            vel[i] = _velocity_from_positions(pos[:, :2], valid[i])
            derived += 1
        else:
            vp = _points(o["velocity"], f"{w}.velocity", dims=2)
            if vp.shape[0] != t:
                raise _Bad(f"{w}.velocity: {vp.shape[0]} steps, the scene has {t}")
            vel[i] = vp
        size[i] = [_num(o.get(k, 0.0 if k == "height" else None), f"{w}.{k}")
                   for k in ("length", "width", "height")]
    if len(set(ids.tolist())) != n:
        dup = next(x for x in ids.tolist() if (ids == x).sum() > 1)
        raise _Bad(f"objects: id {dup} used by more than one object")
    if derived:
        notes.append(f"velocity derived from positions for {derived} object(s) without one")
    tile = lambda c: np.repeat(size[:, c:c + 1], t, axis=1)  # noqa: E731
    return Tracks(ids, types, xyz[..., 0], xyz[..., 1], xyz[..., 2], tile(0), tile(1), tile(2),
                  heading, vel[..., 0], vel[..., 1], valid), t


def _roadmap(roads: list, notes: list[str]) -> RoadMap:
    lanes, lines, edges, stops, walks, bumps, drives = [], [], [], [], [], [], []
    skipped: dict[str, int] = {}
    for i, raw in enumerate(roads):
        w = f"roads[{i}]"
        r = _dict(raw, w)
        rid = _int(r.get("id", i), f"{w}.id")
        kind = r.get("type")
        code = r.get("map_element_id")
        code = None if code is None else _int(code, f"{w}.map_element_id")
        geom = _points(r.get("geometry"), f"{w}.geometry")
        if kind == "lane":
            lt = LaneType(code) if code in (0, 1, 2, 3) else LaneType.UNDEFINED
            lanes.append(Lane(rid, geom, lt))
        elif kind == "road_line":
            c = None if code is None else code - ROAD_LINE_OFFSET
            lines.append(RoadLine(rid, geom, RoadLineType(c) if c in set(RoadLineType)
                                  else RoadLineType.UNKNOWN))
        elif kind == "road_edge":
            c = None if code is None else code - ROAD_EDGE_OFFSET
            edges.append(RoadEdge(rid, geom, RoadEdgeType(c) if c in set(RoadEdgeType)
                                  else RoadEdgeType.UNKNOWN))
        elif kind == "stop_sign":
            if geom.shape[0] == 0:
                raise _Bad(f"{w}.geometry: a stop sign needs a position")
            stops.append(StopSign(rid, (), geom[:1]))
        elif kind in ("crosswalk", "speed_bump", "driveway"):
            cls = {"crosswalk": Crosswalk, "speed_bump": SpeedBump, "driveway": Driveway}[kind]
            (walks if kind == "crosswalk" else bumps if kind == "speed_bump" else drives) \
                .append(cls(rid, geom))
        else:
            skipped[str(kind)] = skipped.get(str(kind), 0) + 1
    for kind, k in skipped.items():
        notes.append(f"{k} road feature(s) of unknown type {printable(kind, 40)!r} skipped")
    return RoadMap(tuple(lanes), tuple(lines), tuple(edges), tuple(stops), tuple(walks),
                   tuple(bumps), tuple(drives))


def _state(v: Any, where: str) -> int:
    if isinstance(v, str):
        name = v.upper().removeprefix("LANE_STATE_")
        if name not in _STATE_NAMES:
            raise _Bad(f"{where}: unknown signal state {printable(v, 40)!r}")
        return int(_STATE_NAMES[name])
    s = _int(v, where)
    if s not in set(SignalState):
        raise _Bad(f"{where}: signal state {s} out of range 0..8")
    return s


def _signals(tl: Any, t: int, lane_ends: dict[int, np.ndarray], notes: list[str]
             ) -> SignalStates:
    """Per-lane state series (module doc); anything else dropped with a note. A state's stop
    point is the entry's ``x`` / ``y`` at that step, else the lane's last point."""
    if not tl:
        return SignalStates.empty()
    if not isinstance(tl, dict) or not all(isinstance(v, dict) and isinstance(v.get("state"),
                                                                               list)
                                           for v in tl.values()):
        notes.append("tl_states in a layout this reader does not know: signal states dropped")
        return SignalStates.empty()
    rows = []
    for key, entry in tl.items():
        try:
            lane = int(key)
        except ValueError:
            raise _Bad(f"tl_states[{printable(str(key), 40)!r}]: not a lane id") from None
        if lane not in lane_ends:
            notes.append(f"tl_states: lane {lane} not in the map: its states dropped")
            continue
        states = entry["state"][:t]
        xs, ys = entry.get("x"), entry.get("y")
        for k, s in enumerate(states):
            if s is None:  # no record at this step
                continue
            code = _state(s, f"tl_states[{lane}].state[{k}]")
            x = xs[k] if isinstance(xs, list) and k < len(xs) else None
            y = ys[k] if isinstance(ys, list) and k < len(ys) else None
            if isinstance(x, (int, float)) and isinstance(y, (int, float)) \
                    and np.isfinite(x) and np.isfinite(y):
                pt = (float(x), float(y), float(lane_ends[lane][2]))
            else:
                pt = tuple(float(c) for c in lane_ends[lane])
            rows.append((k, lane, code, pt))
    if not rows:
        return SignalStates.empty()
    rows.sort(key=lambda r: r[0])  # by step (stable: lanes in recorded order within a step)
    step, lane, state, point = zip(*rows)
    return SignalStates(np.array(step), np.array(lane), np.array(state), np.array(point))


def scene_from_gpudrive(data: Any, source: str = "") -> Scene:
    """The :class:`~magail_sumo.scene.Scene` of a parsed GPUDrive JSON document (module doc);
    :class:`SceneValidationError` naming the field otherwise."""
    try:
        doc = _dict(data, "document")
        notes: list[str] = []
        tracks, t = _tracks(_list(doc.get("objects"), "objects"), notes)
        roadmap = _roadmap(_list(doc.get("roads", []), "roads"), notes)
        meta = _dict(doc.get("metadata", {}), "metadata")
        sid = doc.get("scenario_id") or meta.get("scenario_id") or Path(source).stem
        if not isinstance(sid, str) or not sid:
            raise _Bad("scenario_id: expected a non-empty string")
        sdc = _int(meta.get("sdc_track_index", -1), "metadata.sdc_track_index")
        if not -1 <= sdc < tracks.num_tracks:
            raise _Bad(f"metadata.sdc_track_index: {sdc} is not an object index "
                       f"(0..{tracks.num_tracks - 1})")
        predictions = []
        for k, p in enumerate(_list(meta.get("tracks_to_predict", []),
                                    "metadata.tracks_to_predict")):
            w = f"metadata.tracks_to_predict[{k}]"
            p = _dict(p, w)
            predictions.append(RequiredPrediction(_int(p.get("track_index"), w + ".track_index"),
                                                  _int(p.get("difficulty", 0), w + ".difficulty")))
        interest = tuple(_int(v, "metadata.objects_of_interest")
                         for v in _list(meta.get("objects_of_interest", []),
                                        "metadata.objects_of_interest"))
        current = _int(meta.get("current_time_index", min(WOMD_CURRENT_INDEX, t - 1)),
                       "metadata.current_time_index")
        signals = _signals(doc.get("tl_states"), t,
                           {l.id: l.polyline[-1] for l in roadmap.lanes if len(l.polyline)},
                           notes)
    except _Bad as exc:
        raise SceneValidationError(str(exc)) from None
    successors = neighbors = 0
    if len(roadmap.lanes) > MAX_INFERRED_LANES:
        notes.append(f"no lane connectivity and {len(roadmap.lanes)} lanes (more than "
                     f"{MAX_INFERRED_LANES}): none inferred")
    elif roadmap.lanes:
        lanes, successors, neighbors = infer_lane_connectivity(roadmap.lanes)
        roadmap = dataclasses.replace(roadmap, lanes=lanes)
    return Scene(scenario_id=sid, timestamps=np.arange(t) * STEP, tracks=tracks, roadmap=roadmap,
                 signals=signals, sdc_track_index=sdc, current_time_index=current,
                 tracks_to_predict=tuple(predictions), objects_of_interest=interest,
                 data_quality=DataQuality((), successors, neighbors, tuple(notes)))


def load_gpudrive(path: str | PathLike) -> Scene:
    """Read and validate one GPUDrive JSON scene; :class:`SceneFormatError` naming the file and
    the problem (one line)."""
    p = Path(path)
    try:
        data = read_json(p, FILE_LIMIT, MAX_DEPTH, expected="a GPUDrive JSON scene")
    except InputFileError as exc:
        raise SceneFormatError(p, 0, exc.problem) from None
    try:
        scene = scene_from_gpudrive(data, str(p))
        validate_scene(scene)
    except (SceneValidationError, ValueError) as exc:
        raise SceneFormatError(p, 0, printable(str(exc), 300)) from None
    return scene


def iter_gpudrive(path: str | PathLike) -> Iterator[tuple[int, Scene | SceneFormatError]]:
    """``(0, Scene or SceneFormatError)``: a file holds one scene."""
    try:
        yield 0, load_gpudrive(path)
    except SceneFormatError as exc:
        yield 0, exc
