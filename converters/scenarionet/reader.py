"""Read ScenarioNet scenario pickles (``sd_*.pkl``) into :class:`~magail_sumo.scene.Scene`.

Pickles are loaded only through :mod:`converters.scenarionet.safe_pickle`. The dict layout is
the one ScenarioNet's Waymo converter writes (see ``schema.py``); every value is read through
:mod:`converters.scenarionet.fields`, which checks it and raises an error naming the key path
for a wrong shape or type. This module builds the scene from those values.
"""

from __future__ import annotations

import dataclasses
import os
from os import PathLike
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from converters.files import open_regular
from converters.scenarionet import schema
from converters.scenarionet.fields import (
    PER_ITEM, Ids, as_array, as_bool, as_enum, as_float, as_int, as_int_array, as_list, as_points,
    as_text, charge, describe, memory_budget, or_default, required,
)
from converters.scenarionet.safe_pickle import (
    UnsafePickleError, allocation_budget, safe_loads,
)
from magail_sumo.errors import SceneFormatError
from magail_sumo.outputs import printable
from magail_sumo.scene.connectivity import MAX_LANES as MAX_INFERRED_LANES
from magail_sumo.scene import (
    BoundarySegment, Crosswalk, DataQuality, DroppedReference, Driveway, Lane, LaneNeighbor,
    ObjectType, RequiredPrediction, RoadEdge, RoadLine, RoadMap, Scene, SceneValidationError,
    SignalState, SignalStates, SourceIds, SpeedBump, StopSign, Tracks, drop_tracks,
    infer_lane_connectivity,
    validate_scene,
)

SUMMARY_FILE = "dataset_summary.pkl"
MAPPING_FILE = "dataset_mapping.pkl"

_OBJECT_TYPES = {**schema.inverse(schema.OBJECT_TYPES),
                 **{name: ObjectType.OTHER for name in schema.OTHER_OBJECT_TYPES}}
#: the largest scene pickle read (real ones are tens of MB; read whole into memory)
MAX_PICKLE_BYTES = 1 << 30
_FEATURE_ALIASES = schema.FEATURE_TYPE_ALIASES
_KMH_PER_MPH = 1.609344
_LANE_TYPES = schema.inverse(schema.LANE_TYPES)
_LINE_TYPES = schema.inverse(schema.ROAD_LINE_TYPES)
_BOUNDARY_TYPES = {**schema.inverse(schema.BOUNDARY_TYPES), "UNKNOWN_LINE": 0}
_EDGE_TYPES = schema.inverse(schema.ROAD_EDGE_TYPES)
_SIGNAL_STATES = schema.inverse(schema.SIGNAL_STATES)
_AREA_TYPES = {schema.CROSSWALK: ("crosswalks", Crosswalk), schema.SPEED_BUMP: ("speed_bumps", SpeedBump),
               schema.DRIVEWAY: ("driveways", Driveway)}


def scene_from_scenarionet(sd: Any, budget: int | None = None,
                           keep_synthetic: bool = False) -> Scene:
    """Convert a ScenarioNet scenario dict (no validation beyond structure).

    Both layouts are read: the newer ScenarioNet one (``state.length/width/height``,
    ``metadata``; signals keyed by signal id with string states) and the older MetaDrive one
    (``state.size`` T×3; signals keyed by lane with per-step ``state.lane``/``stop_point`` and
    integer WOMD ``TrafficSignalLaneState`` codes; ``sdc_track_index`` (a track key) and ``ts``
    at the top level, possibly no ``metadata``; areas with a ``polyline`` instead of a
    ``polygon``). Track or map-feature keys that are not integers (nuScenes: UUIDs, ``"ego"``)
    are numbered 0..N-1 in recorded order, the originals kept in ``Scene.source_ids``.
    References to ids not in the map are dropped and listed in ``Scene.data_quality``; lane
    connectivity is inferred from geometry for a map that has none
    (:func:`~magail_sumo.scene.infer_lane_connectivity`).

    A track the source marks as synthetic (``metadata.selected_adv_id``: safety-critical
    scenes whose adversary's trajectory was generated, not recorded) is not human driving: it
    is dropped (:func:`~magail_sumo.scene.drop_tracks`, noted in ``data_quality``) unless
    ``keep_synthetic``, when it stays with a note naming it.

    :param budget: bytes of memory the scene may take (None: unlimited); exceeding it is a
        :class:`SceneValidationError` raised before the memory is allocated.
    """
    with memory_budget(budget):
        return _scene(sd, keep_synthetic)


def _synthetic_rows(meta: dict, index_of: dict[str, int]) -> list[tuple[int, str]]:
    """(row, original id) of the tracks ``metadata.selected_adv_id`` names (one id or a
    list); ids that are not tracks are ignored."""
    raw = meta.get("selected_adv_id")
    if raw is None:
        return []
    values = raw if isinstance(raw, (list, tuple)) else [raw]
    out = []
    for v in values:
        key = as_text(v, "metadata.selected_adv_id") if not isinstance(v, (int, np.integer)) \
            else str(int(v))
        if key in index_of:
            out.append((index_of[key], key))
    return out


def _scene(sd: Any, keep_synthetic: bool = False) -> Scene:
    if not isinstance(sd, dict):
        raise SceneValidationError(f"expected a scenario dict, got {type(sd).__name__}")
    meta = sd.get("metadata")
    if meta is None:  # older MetaDrive files: sdc_track_index / ts / id at the top level
        meta = {}
    elif not isinstance(meta, dict):
        raise SceneValidationError(f"metadata: expected a dict, got {type(meta).__name__}")
    notes: list[str] = []
    ts_raw, ts_path = (meta["ts"], "metadata.ts") if "ts" in meta else (sd.get("ts"), "ts")
    if "length" in sd:
        length = as_int(sd["length"], "length")
    elif ts_raw is not None:
        length = len(as_list(ts_raw, ts_path))
    else:
        raise SceneValidationError("missing key 'length' (and no 'ts' to take it from)")
    if length < 0:
        raise SceneValidationError(f"length: {length} is negative")
    if ts_raw is not None:
        ts = as_array(ts_raw, (length,), np.float64, ts_path)
    else:
        ts = np.arange(length) * 0.1
        notes.append("no timestamps (metadata.ts): 0.1 s steps assumed")
    tracks_d = required(sd, "tracks", "")
    if not isinstance(tracks_d, dict):
        raise SceneValidationError("tracks: expected a dict")
    tracks, track_ids = _tracks(tracks_d, length)
    index_of = {name: i for i, name in enumerate(
        track_ids.names if track_ids.renumbered else (str(v) for v in track_ids.ids))}
    sdc_index = _sdc_index(sd, meta, index_of, tracks.num_tracks)
    tracks = _upright_sdc_box(tracks, sdc_index, notes)
    ttp = meta.get("tracks_to_predict")
    if ttp is None or (isinstance(ttp, (list, tuple)) and not ttp):
        ttp = {}
    if not isinstance(ttp, dict):
        raise SceneValidationError("metadata.tracks_to_predict: expected a dict")
    sid = meta["scenario_id"] if "scenario_id" in meta else required(sd, "id", "")
    predictions = []
    for k, v in ttp.items():
        p = f"metadata.tracks_to_predict[{describe(k)}]"
        predictions.append(RequiredPrediction(
            as_int(required(v, "track_index", p), p + ".track_index"),
            as_int(v.get("difficulty", 0), p + ".difficulty")))
    dropped: list[DroppedReference] = []
    interest = []
    for v in as_list(meta.get("objects_of_interest"), "metadata.objects_of_interest"):
        if not track_ids.renumbered:
            interest.append(as_int(v, "metadata.objects_of_interest"))
            continue
        name = as_text(v, "metadata.objects_of_interest")
        if name in index_of:
            interest.append(index_of[name])
        else:
            dropped.append(DroppedReference(-1, "objects_of_interest", name))
    roadmap, feature_ids = _roadmap(required(sd, "map_features", ""), dropped, notes)
    signals = _signals(required(sd, "dynamic_map_states", ""), length, feature_ids, dropped, notes)
    successors = neighbors = 0
    lanes = roadmap.lanes
    no_links = not any(l.entry_lanes or l.exit_lanes for l in lanes)
    no_neighbors = not any(l.left_neighbors or l.right_neighbors for l in lanes)
    if len(lanes) > MAX_INFERRED_LANES and (no_links or no_neighbors):
        notes.append(f"no lane connectivity and {len(lanes)} lanes (more than "
                     f"{MAX_INFERRED_LANES}): none inferred")
    elif lanes and (no_links or no_neighbors):
        inferred, successors, neighbors = infer_lane_connectivity(lanes, successors=no_links,
                                                                  neighbors=no_neighbors)
        roadmap = dataclasses.replace(roadmap, lanes=inferred)
    scene = Scene(
        scenario_id=as_text(sid, "metadata.scenario_id"),
        timestamps=ts,
        tracks=tracks,
        roadmap=roadmap,
        signals=signals,
        sdc_track_index=sdc_index,
        current_time_index=as_int(meta.get("current_time_index", 0), "metadata.current_time_index"),
        tracks_to_predict=tuple(predictions),
        objects_of_interest=tuple(interest),
        source_ids=SourceIds(track_ids.pairs(), feature_ids.pairs()),
        data_quality=DataQuality(tuple(dropped), successors, neighbors, tuple(notes)),
    )
    synthetic = _synthetic_rows(meta, index_of)
    if not synthetic:
        return scene
    names = ", ".join(k for _, k in synthetic)
    if keep_synthetic:
        return dataclasses.replace(scene, data_quality=dataclasses.replace(
            scene.data_quality, notes=(*scene.data_quality.notes, f"synthetic track(s) {names} "
                                       "(metadata.selected_adv_id) kept on request")))
    return drop_tracks(scene, [r for r, _ in synthetic],
                       f"synthetic track(s) {names} (metadata.selected_adv_id: generated, not "
                       "recorded) dropped: not human driving")


def _upright_sdc_box(tracks: Tracks, sdc: int, notes: list[str]) -> Tracks:
    """The tracks with the recording vehicle's box length and width swapped when its box is
    wider than long (median over its valid states): ScenarioNet's nuScenes converter writes the
    ego's size as 1.73 m long and 4.08 m wide (metadriverse/scenarionet#68), which puts a
    sideways box into every collision and overlap test. Noted in ``notes``; other tracks are
    kept as recorded."""
    if not 0 <= sdc < tracks.num_tracks or int(tracks.type[sdc]) != int(ObjectType.VEHICLE):
        return tracks
    v = tracks.valid[sdc]
    if not v.any():
        return tracks
    length, width = float(np.median(tracks.length[sdc, v])), float(np.median(tracks.width[sdc, v]))
    if not length < width:
        return tracks
    new_length, new_width = tracks.length.copy(), tracks.width.copy()
    new_length[sdc], new_width[sdc] = tracks.width[sdc], tracks.length[sdc]
    notes.append(f"sdc box wider than long ({length:.2f} m x {width:.2f} m): length and width "
                 "swapped")
    return dataclasses.replace(tracks, length=new_length, width=new_width)


def _sdc_index(sd: dict, meta: dict, index_of: dict[str, int], n: int) -> int:
    """Index of the recording vehicle: ``metadata.sdc_track_index``, else the track keyed
    ``metadata.sdc_id``, else the older layout's top-level ``sdc_track_index`` (a track key;
    an index when no track has that key); -1 when none is given."""
    if meta.get("sdc_track_index") is not None:
        return as_int(meta["sdc_track_index"], "metadata.sdc_track_index")
    for value, path in ((meta.get("sdc_id"), "metadata.sdc_id"), (sd.get("sdc_id"), "sdc_id"),
                        (sd.get("sdc_track_index"), "sdc_track_index")):
        if value is None:
            continue
        key = as_text(value, path)
        if key in index_of:
            return index_of[key]
        if path == "sdc_track_index":
            return as_int(value, path)
        return -1  # an sdc id that is not a track (as before: no sdc)
    return -1


def _tracks(tracks_d: dict, length: int) -> tuple[Tracks, Ids]:
    n = len(tracks_d)
    charge(PER_ITEM * n * length, "tracks")
    cols: dict[str, np.ndarray] = {k: np.zeros((n, length), np.float64) for k in ("x", "y", "z")}
    cols.update({k: np.zeros((n, length), np.float32)
                 for k in ("length", "width", "height", "heading", "vx", "vy")})
    valid = np.zeros((n, length), bool)
    types = np.zeros(n, np.int8)
    keys = list(tracks_d)
    track_ids = Ids(keys, "tracks")
    for i, key in enumerate(keys):
        obj = tracks_d[key]
        path = f"tracks[{describe(key)}]"
        types[i] = as_enum(required(obj, "type", path), _OBJECT_TYPES, path + ".type")
        state = required(obj, "state", path)
        sp = path + ".state"
        pos = as_array(required(state, "position", sp), (length, -1), np.float64, sp + ".position")
        if pos.shape[1] not in (2, 3):
            raise SceneValidationError(f"{sp}.position: expected 2 or 3 columns, "
                                       f"got {pos.shape[1]}")
        cols["x"][i], cols["y"][i] = pos[:, 0], pos[:, 1]
        if pos.shape[1] == 3:
            cols["z"][i] = pos[:, 2]
        if isinstance(state, dict) and "size" in state and "length" not in state:
            size = as_array(state["size"], (length, -1), np.float32, sp + ".size")  # older layout
            if size.shape[1] not in (2, 3):
                raise SceneValidationError(f"{sp}.size: expected 2 or 3 columns (length, width, "
                                           f"height), got {size.shape[1]}")
            cols["length"][i], cols["width"][i] = size[:, 0], size[:, 1]
            if size.shape[1] == 3:
                cols["height"][i] = size[:, 2]
        else:
            for name in ("length", "width", "height"):
                if name in state:
                    cols[name][i] = as_array(state[name], (length,), np.float32, f"{sp}.{name}")
        cols["heading"][i] = as_array(required(state, "heading", sp), (length,), np.float32,
                                      sp + ".heading")
        if "velocity" in state:
            vel = as_array(state["velocity"], (length, 2), np.float32, sp + ".velocity")
            cols["vx"][i], cols["vy"][i] = vel[:, 0], vel[:, 1]
        valid[i] = as_array(required(state, "valid", sp), (length,), bool, sp + ".valid")
    return Tracks(id=np.array(track_ids.ids, np.int64), type=types, valid=valid, **cols), track_ids


class _Refs:
    """Resolves a map's references; one to an id not in the map is dropped and recorded."""

    def __init__(self, ids: Ids, lane_ids: set[int], all_ids: set[int],
                 dropped: list[DroppedReference]) -> None:
        self.ids, self.lane_ids, self.all_ids, self.dropped = ids, lane_ids, all_ids, dropped

    def __call__(self, value: Any, owner: int, field: str, path: str,
                 lanes_only: bool = True) -> int | None:
        if self.ids.names is None:  # fast path: integer ids
            fid: int | None = value if type(value) is int else as_int(value, path)
            name = None
        else:
            fid, name = self.ids.resolve(value, path)
        if fid is None or fid not in (self.lane_ids if lanes_only else self.all_ids):
            self.dropped.append(DroppedReference(owner, field, str(fid) if name is None else name))
            return None
        return fid

    def lanes(self, items: Any, owner: int, field: str, path: str) -> tuple[int, ...]:
        out = (self(v, owner, field, path) for v in as_list(items, path))
        return tuple(v for v in out if v is not None)


def _segments(items: Any, path: str, refs: _Refs, owner: int, field: str,
              check: bool = True) -> tuple[BoundarySegment, ...]:
    """Boundary segments; ``check=False`` (a neighbour's boundaries, where 0 means unset) keeps
    unknown integer ids as recorded."""
    out = []
    for j, seg in enumerate(as_list(items, path)):
        p = f"{path}[{j}]"
        raw = required(seg, "boundary_feature_id", p)
        if check or refs.ids.renumbered:
            fid = refs(raw, owner, field, p + ".boundary_feature_id", lanes_only=False)
            if fid is None:
                continue
        else:
            fid = as_int(raw, p + ".boundary_feature_id")
        out.append(BoundarySegment(
            as_int(required(seg, "lane_start_index", p), p + ".lane_start_index"),
            as_int(required(seg, "lane_end_index", p), p + ".lane_end_index"),
            fid,
            as_enum(seg.get("boundary_type", "UNKNOWN"), _BOUNDARY_TYPES, p + ".boundary_type"),
        ))
    return tuple(out)


def _neighbors(items: Any, path: str, refs: _Refs, owner: int,
               field: str) -> tuple[LaneNeighbor, ...]:
    out = []
    bfield = field + ".boundaries"
    for j, nb in enumerate(as_list(items, path)):
        p = f"{path}[{j}]"
        fid = refs(required(nb, "feature_id", p), owner, field, p + ".feature_id")
        if fid is None:
            continue
        indices = [as_int(required(nb, k, p), f"{p}.{k}") for k in
                   ("self_start_index", "self_end_index", "neighbor_start_index",
                    "neighbor_end_index")]
        out.append(LaneNeighbor(fid, *indices, boundaries=_segments(
            nb.get("boundaries"), p + ".boundaries", refs, owner, bfield, check=False)))
    return tuple(out)


def _speed_mph(f: dict, path: str) -> float:
    if f.get("speed_limit_mph") is not None:
        return as_float(f["speed_limit_mph"], path + ".speed_limit_mph")
    if f.get("speed_limit_kmh") is not None:  # nuScenes and other non-WOMD datasets
        return as_float(f["speed_limit_kmh"], path + ".speed_limit_kmh") / _KMH_PER_MPH
    return 0.0


#: m, a lane's centre line whose points lie this far on average from its own polygon's is in
#: another frame (see :func:`_lanes_on_polygons`)
FRAME_SHIFT_MIN = 50.0
#: m, the shifted lanes' offsets agree within this of their median (the mean of a polygon's
#: vertices is not its centre: a long irregular outline puts it metres off the centre line)
FRAME_SHIFT_AGREE = 25.0


def _lanes_on_polygons(lanes: list[Lane], polygons: dict[int, np.ndarray],
                       notes: list[str]) -> list[Lane]:
    """Lanes whose centre line is offset from their own polygon by one common vector, moved
    onto their polygons.

    Seen in ScenarioNet's nuScenes trainval pickles: the centre lines of the lanes that have a
    polygon (nuScenes "lane"; "lane_connector"s have none) are in a frame centred on the ego's
    first position, while their polygons, the connectors, road edges and tracks are in the map
    frame, so every lane link joins two lanes kilometres apart and the road lanes lie off the
    recorded driving. The offset of a lane is the mean of its polygon's points minus the mean of
    its centre line's points; when nine in ten of those above :data:`FRAME_SHIFT_MIN` m agree
    within :data:`FRAME_SHIFT_AGREE` m of their median, the frames differ by that median (x, y)
    -- or, where lane links join lanes of the two frames, by the median gap of those links,
    which is exact -- and every far lane nearer that offset than no offset is moved by it; the
    repair is noted. Anything else is left as recorded."""
    offsets = {lane.id: polygons[lane.id][:, :2].mean(0) - lane.polyline[:, :2].mean(0)
               for lane in lanes if len(polygons.get(lane.id, ())) and len(lane.polyline)}
    far = {fid: o for fid, o in offsets.items() if np.hypot(*o) > FRAME_SHIFT_MIN}
    if not far:
        return lanes
    shift = np.median(np.array(list(far.values())), axis=0)
    agree = {fid for fid, o in far.items() if np.hypot(*(o - shift)) <= FRAME_SHIFT_AGREE}
    if len(agree) < 0.9 * len(far):
        return lanes  # no common frame: left as recorded
    # a polygon's vertex mean is only near its centre line; a link from a lane in the one
    # frame to a lane in the other gives the offset exactly (end meets start)
    by_id = {lane.id: lane for lane in lanes}
    gaps = [(by_id[e].polyline[0, :2] - lane.polyline[-1, :2]) * (1 if lane.id in agree else -1)
            for lane in lanes for e in lane.exit_lanes
            if e in by_id and (lane.id in agree) != (e in agree)]
    if gaps and np.hypot(*(np.median(gaps, axis=0) - shift)) <= FRAME_SHIFT_AGREE:
        shift = np.median(gaps, axis=0)
    # with the frame established, every far lane nearer the shifted frame than its own moves
    # (a long curved lane's vertex mean can lie 30 m off its centre line)
    agree = {fid for fid, o in far.items() if np.hypot(*(o - shift)) < np.hypot(*o) / 2}
    notes.append(f"{len(agree)} lane centre lines lay ({shift[0]:.1f}, {shift[1]:.1f}) m off "
                 "their own polygons (another frame): moved onto them")
    step = np.array([shift[0], shift[1], 0.0])
    return [dataclasses.replace(lane, polyline=lane.polyline + step[:lane.polyline.shape[1]])
            if lane.id in agree else lane for lane in lanes]


def _roadmap(features: Any, dropped: list[DroppedReference],
             notes: list[str] | None = None) -> tuple[RoadMap, Ids]:
    """The map; a lane frame repair (:func:`_lanes_on_polygons`) is noted in ``notes``."""
    if not isinstance(features, dict):
        raise SceneValidationError("map_features: expected a dict")
    kinds: dict[str, list] = {k: [] for k in ("lanes", "road_lines", "road_edges", "stop_signs",
                                              "crosswalks", "speed_bumps", "driveways")}
    keys = list(features)
    ids = Ids(keys, "map_features")
    ftypes = []
    for key in keys:
        path = f"map_features[{describe(key)}]"
        ftype = required(features[key], "type", path)
        if not isinstance(ftype, str):
            raise SceneValidationError(f"{path}.type: expected a string, got {describe(ftype)}")
        ftypes.append(_FEATURE_ALIASES.get(ftype, ftype))
    lane_ids = {fid for fid, t in zip(ids.ids, ftypes) if t in _LANE_TYPES}
    refs = _Refs(ids, lane_ids, set(ids.ids), dropped)
    polygons: dict[int, np.ndarray] = {}  # lanes' own polygons (nuScenes), for the frame check
    for key, fid, ftype in zip(keys, ids.ids, ftypes):
        f = features[key]
        path = f"map_features[{describe(key)}]"
        if ftype in _LANE_TYPES:
            if isinstance(f, dict) and f.get("polygon") is not None:
                try:  # only the frame check reads it: a bad one leaves that lane unchecked
                    polygons[fid] = as_points(f["polygon"], path + ".polygon")
                except SceneValidationError:
                    pass
            kinds["lanes"].append(Lane(
                id=fid, polyline=as_points(required(f, "polyline", path), path + ".polyline"),
                type=_LANE_TYPES[ftype],
                speed_limit_mph=_speed_mph(f, path),
                interpolating=as_bool(f.get("interpolating", False), path + ".interpolating"),
                entry_lanes=refs.lanes(f.get("entry_lanes"), fid, "entry_lanes",
                                       path + ".entry_lanes"),
                exit_lanes=refs.lanes(f.get("exit_lanes"), fid, "exit_lanes", path + ".exit_lanes"),
                left_neighbors=_neighbors(f.get("left_neighbor"), path + ".left_neighbor", refs,
                                          fid, "left_neighbor"),
                right_neighbors=_neighbors(f.get("right_neighbor"), path + ".right_neighbor", refs,
                                           fid, "right_neighbor"),
                left_boundaries=_segments(f.get("left_boundaries"), path + ".left_boundaries",
                                          refs, fid, "left_boundaries"),
                right_boundaries=_segments(f.get("right_boundaries"), path + ".right_boundaries",
                                           refs, fid, "right_boundaries"),
            ))
        elif ftype in _LINE_TYPES:
            line = as_points(required(f, "polyline", path), path + ".polyline")
            kinds["road_lines"].append(RoadLine(fid, line, _LINE_TYPES[ftype]))
        elif ftype in _EDGE_TYPES:
            if isinstance(f, dict) and f.get("polyline") is None and f.get("polygon") is not None:
                # nuScenes trainval sidewalks (ROAD_EDGE_SIDEWALK) come as areas: the edge is
                # their closed outline
                area = as_points(f["polygon"], path + ".polygon")
                line = np.concatenate([area, area[:1]]) if len(area) else area
            else:
                line = as_points(required(f, "polyline", path), path + ".polyline")
            kinds["road_edges"].append(RoadEdge(fid, line, _EDGE_TYPES[ftype]))
        elif ftype == schema.STOP_SIGN:
            pos = as_array(required(f, "position", path), (-1,), np.float64, path + ".position")
            if pos.shape[0] > 3:
                raise SceneValidationError(f"{path}.position: expected 3 coordinates, "
                                           f"got {pos.shape[0]}")
            kinds["stop_signs"].append(StopSign(
                fid, refs.lanes(f.get("lane"), fid, "lane", path + ".lane"),
                np.pad(pos, (0, 3 - pos.shape[0])) if pos.shape[0] < 3 else pos))
        elif ftype in _AREA_TYPES:
            kind, cls = _AREA_TYPES[ftype]
            # the older MetaDrive layout stores an area's outline as "polyline"
            outline = f.get("polygon") if isinstance(f, dict) and f.get("polygon") is not None \
                else (f.get("polyline") if isinstance(f, dict) else None)
            points = (as_points(outline, path + ".polygon") if outline is not None
                      else np.zeros((0, 3)))
            kinds[kind].append(cls(fid, points))
        else:
            raise SceneValidationError(f"{path}: unsupported map feature type {ftype!r}")
    if polygons:
        kinds["lanes"] = _lanes_on_polygons(kinds["lanes"], polygons,
                                            notes if notes is not None else [])
    return RoadMap(**{k: tuple(v) for k, v in kinds.items()}), ids


def _signal_state(value: Any, path: str) -> int:
    """A signal state: a ``LANE_STATE_*`` name, or the older layout's integer WOMD
    ``TrafficSignalLaneState`` code (0 unknown .. 8 flashing caution; same values as ours)."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)):
        if not 0 <= value <= max(SignalState):
            raise SceneValidationError(f"{path}: unknown signal state code {describe(value)}")
        return int(value)
    return as_enum(value, _SIGNAL_STATES, path)


def _signals(dyn: Any, length: int, map_ids: Ids, dropped: list[DroppedReference],
             notes: list[str]) -> SignalStates:
    if not isinstance(dyn, dict):
        raise SceneValidationError("dynamic_map_states: expected a dict")
    charge(PER_ITEM * length, "dynamic_map_states")
    per_step: list[list[tuple[int, int, np.ndarray]]] = [[] for _ in range(length)]
    older_steps: set[int] = set()

    def lane_id(value: Any, path: str) -> int | None:
        fid, name = map_ids.resolve(value, path)
        if fid is None:  # only for a map with named features (integer ids are kept as recorded)
            dropped.append(DroppedReference(-1, "dynamic_map_states.lane", name))
        return fid

    for key, light in dyn.items():
        path = f"dynamic_map_states[{describe(key)}]"
        if not isinstance(light, dict):
            raise SceneValidationError(f"{path}: expected a dict, got {type(light).__name__}")
        state = required(light, "state", path)
        sp = path + ".state"
        if isinstance(state, dict) and "lane" in state and "lane" not in light:
            # older MetaDrive layout: per-step lane ids (0 = no record) and stop points
            lanes = as_int_array(state["lane"], length, sp + ".lane")
            codes = as_int_array(required(state, "object_state", sp), length, sp + ".object_state")
            stops = as_array(required(state, "stop_point", sp), (length, -1), np.float64,
                           sp + ".stop_point")
            if stops.shape[1] < 3:
                stops = np.pad(stops, ((0, 0), (0, 3 - stops.shape[1])))
            for t in np.flatnonzero(lanes != 0).tolist():
                lane = lane_id(int(lanes[t]), sp + ".lane")
                if lane is not None:
                    per_step[t].append((lane, _signal_state(int(codes[t]), f"{sp}[{t}]"),
                                        stops[t, :3]))
                    older_steps.add(t)
            continue
        lane = lane_id(light.get("lane", key), path + ".lane")
        states = as_list(required(state, "object_state", sp), sp + ".object_state")
        if len(states) != length:
            raise SceneValidationError(
                f"{path}.state.object_state: expected {length} steps, got {len(states)}")
        stop = as_array(light.get("stop_point", np.zeros(3)), (-1,), np.float64,
                        path + ".stop_point")
        stop = np.pad(stop, (0, 3 - stop.shape[0])) if stop.shape[0] < 3 else stop[:3]
        if lane is None:
            continue
        for t, s in enumerate(states):
            if s is not None:
                per_step[t].append((lane, _signal_state(s, f"{path}.state[{t}]"), stop))
    if older_steps:
        notes.append(f"older MetaDrive signal layout: states recorded at {len(older_steps)} of "
                     f"{length} steps")
    rows = [(t, lane, s, p) for t, recs in enumerate(per_step) for lane, s, p in recs]
    if not rows:
        return SignalStates.empty()
    step, lane, state, point = zip(*rows)
    return SignalStates(np.array(step), np.array(lane), np.array(state), np.array(point))


# ------------------------------------------------------------------ files

def load_scenarionet(path: str | PathLike, keep_synthetic: bool = False) -> Scene:
    """Load and validate one ScenarioNet pickle (restricted unpickler).

    :raises SceneFormatError: naming the file and the problem (one line).
    """
    p = Path(path)
    with open_regular(p) as fh:  # SceneFormatError for a FIFO, device, loop...; OSError
        size = os.fstat(fh.fileno()).st_size
        if size > MAX_PICKLE_BYTES:
            raise SceneFormatError(p, 0, f"{size / 2**30:.1f} GiB, more than the "
                                         f"{MAX_PICKLE_BYTES >> 30} GiB a scene pickle may be")
        data = fh.read(size + 1)  # not the cap: read(n) allocates n bytes up front
    if len(data) > MAX_PICKLE_BYTES:
        raise SceneFormatError(p, 0, "grew past the size a scene pickle may be while read")
    try:
        sd = safe_loads(data)
    except UnsafePickleError as exc:
        raise SceneFormatError(p, 0, f"unsafe pickle, nothing executed: "
                                     f"{printable(str(exc), 300)}") from None
    except Exception as exc:  # LOAD_ERRORS, or anything else a malformed file provokes
        raise SceneFormatError(p, 0, f"unreadable pickle ({_reason(exc)})") from None
    try:
        scene = scene_from_scenarionet(sd, allocation_budget(len(data)), keep_synthetic)
        validate_scene(scene)
    except SceneValidationError as exc:
        raise SceneFormatError(p, 0, printable(str(exc), 300)) from None
    except Exception as exc:  # a structure the field checks did not foresee
        raise SceneFormatError(p, 0, f"unexpected scenario structure ({_reason(exc)})") from None
    return scene


def _reason(exc: BaseException) -> str:
    text = str(exc)
    if isinstance(exc, RecursionError):
        text = "nested too deeply"
    return printable(f"{type(exc).__name__}: {text}" if text else type(exc).__name__, 200)


def dataset_files(folder: str | PathLike) -> list[Path]:
    """Scenario files of a ScenarioNet dataset folder, from its summary and mapping.

    File names must be plain names (no path separators, not ``.``/``..``) and mapped folders
    relative paths inside the dataset; anything else is a :class:`SceneFormatError`.
    """
    root = Path(folder)

    def load(name: str) -> Any:
        with open_regular(root / name) as fh:  # SceneFormatError for a FIFO, a loop, ...
            data = fh.read()
        try:
            return safe_loads(data)
        except Exception as exc:  # LOAD_ERRORS, UnsafePickleError, anything else
            raise SceneFormatError(root / name, None,
                                   f"unreadable dataset summary ({_reason(exc)})") from None

    summary = load(SUMMARY_FILE)
    mapping = or_default(load(MAPPING_FILE), {}) if (root / MAPPING_FILE).exists() else {}
    if not isinstance(summary, dict) or not isinstance(mapping, dict):
        raise SceneFormatError(root, None, "dataset summary/mapping is not a dict")
    files = []
    for name in summary:
        sub = mapping.get(name, "")
        if not isinstance(name, str) or not isinstance(sub, str) or name in ("", ".", "..") \
                or "/" in name or "\\" in name or "\0" in name + sub or Path(sub).is_absolute() \
                or ".." in Path(sub).parts:
            raise SceneFormatError(root / SUMMARY_FILE, None,
                                   f"bad scenario file name {describe(name)} "
                                   f"(folder {describe(sub)})")
        files.append(root / sub / name)
    return files


def iter_scenarionet(path: str | PathLike, keep_synthetic: bool = False
                     ) -> Iterator[tuple[int, Scene | SceneFormatError]]:
    """Yield ``(index, Scene or SceneFormatError)`` for a pickle or a dataset folder
    (``keep_synthetic``: :func:`scene_from_scenarionet`)."""
    p = Path(path)
    files = dataset_files(p) if p.is_dir() else [p]
    for i, f in enumerate(files):
        try:
            yield i, load_scenarionet(f, keep_synthetic)
        except SceneFormatError as exc:
            yield i, exc
        except OSError as exc:
            yield i, SceneFormatError(f, None, f"cannot read ({exc.strerror or exc})")
