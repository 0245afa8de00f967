"""Read ScenarioNet scenario pickles (``sd_*.pkl``) into :class:`~magail_sumo.scene.Scene`.

Pickles are loaded only through :mod:`converters.scenarionet.safe_pickle`. The dict layout is
the one ScenarioNet's Waymo converter writes (see ``schema.py``); every access is checked and a
wrong shape or type raises an error naming the key path.
"""

from __future__ import annotations

import contextvars
import dataclasses
from os import PathLike
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from converters.files import open_regular
from converters.scenarionet import schema
from converters.scenarionet.safe_pickle import (
    UnsafePickleError, allocation_budget, safe_loads,
)
from magail_sumo.errors import SceneFormatError
from magail_sumo.outputs import printable
from magail_sumo.scene.connectivity import MAX_LANES as MAX_INFERRED_LANES
from magail_sumo.scene import (
    BoundarySegment, Crosswalk, DataQuality, DroppedReference, Driveway, Lane, LaneNeighbor,
    ObjectType, RequiredPrediction, RoadEdge, RoadLine, RoadMap, Scene, SceneValidationError,
    SignalState, SignalStates, SourceIds, SpeedBump, StopSign, Tracks, infer_lane_connectivity,
    validate_scene,
)

SUMMARY_FILE = "dataset_summary.pkl"
MAPPING_FILE = "dataset_mapping.pkl"

_OBJECT_TYPES = {**schema.inverse(schema.OBJECT_TYPES),
                 **{name: ObjectType.OTHER for name in schema.OTHER_OBJECT_TYPES}}
_FEATURE_ALIASES = schema.FEATURE_TYPE_ALIASES
_KMH_PER_MPH = 1.609344
_LANE_TYPES = schema.inverse(schema.LANE_TYPES)
_LINE_TYPES = schema.inverse(schema.ROAD_LINE_TYPES)
_BOUNDARY_TYPES = {**schema.inverse(schema.BOUNDARY_TYPES), "UNKNOWN_LINE": 0}
_EDGE_TYPES = schema.inverse(schema.ROAD_EDGE_TYPES)
_SIGNAL_STATES = schema.inverse(schema.SIGNAL_STATES)
_AREA_TYPES = {schema.CROSSWALK: ("crosswalks", Crosswalk), schema.SPEED_BUMP: ("speed_bumps", SpeedBump),
               schema.DRIVEWAY: ("driveways", Driveway)}


_INT64 = (-(1 << 63), (1 << 63) - 1)
#: Bytes of memory the scene being converted may still take (None: unlimited). A pickle can
#: reference one array or list from many places (its memo), so a small file can describe a
#: huge scene; :func:`load_scenarionet` sets the same budget as the unpickler's
#: (:func:`~converters.scenarionet.safe_pickle.allocation_budget` of the file size).
_BUDGET: contextvars.ContextVar[list[int] | None] = contextvars.ContextVar("budget", default=None)
_PER_ITEM = 64  # bytes charged per list item / per track state
_F32_MAX = float(np.finfo(np.float32).max)


def _describe(value: Any) -> str:
    """A short one-line rendering of ``value`` for a message (never a deep or huge repr)."""
    if type(value) is str and len(value) <= 40 and value.isprintable():
        return repr(value)  # fast path: dict keys of real files
    if isinstance(value, (str, bytes, int, float, bool, type(None), np.number, np.bool_)):
        try:
            return printable(repr(value), 60)
        except ValueError:  # an int too large to print
            return f"an int of {value.bit_length()} bits"  # type: ignore[union-attr]
    if isinstance(value, np.ndarray):
        return f"an array of shape {value.shape}"
    name = type(value).__name__
    return f"{'an' if name[:1] in 'aeiou' else 'a'} {name}"


def _charge(nbytes: int, path: str) -> None:
    budget = _BUDGET.get()
    if budget is None:
        return
    budget[1] -= nbytes
    if budget[1] < 0:
        raise SceneValidationError(
            f"{path}: the scene would take more than {budget[0]} bytes of memory (the limit for "
            "this file's size; its arrays or lists are shared between many fields)")


def _get(d: Any, key: str, path: str) -> Any:
    where = f"{path}: " if path else ""
    if not isinstance(d, dict):
        raise SceneValidationError(f"{where}expected a dict, got {type(d).__name__}")
    if key not in d:
        raise SceneValidationError(f"{where}missing key '{key}'")
    return d[key]


def _array(value: Any, shape: tuple[int, ...], dtype: Any, path: str) -> np.ndarray:
    try:
        arr = np.asarray(value)
        kind = arr.dtype.kind
        if kind not in "biuf":
            raise TypeError(f"dtype {arr.dtype}")
        narrowing = dtype is np.float32 and kind == "f" and arr.dtype.itemsize > 4
        if narrowing:
            with np.errstate(over="ignore"):  # overflow is reported below
                out = arr.astype(dtype)
        else:
            out = arr.astype(dtype, copy=False)
    except (TypeError, ValueError, OverflowError, RecursionError) as exc:
        raise SceneValidationError(f"{path}: expected a numeric array "
                                   f"({printable(str(exc), 80)})") from None
    if narrowing and out.size:
        over = np.isinf(out) & ~np.isinf(arr)  # finite in the file, too large for float32
        if over.any():
            k = int(np.flatnonzero(over.reshape(-1))[0])
            raise SceneValidationError(
                f"{path}: value {arr.reshape(-1)[k]:.6g} out of range (|value| > {_F32_MAX:.4g})")
    arr = out
    if len(shape) == 1 and arr.ndim == 2 and arr.shape[1] == 1:
        arr = arr[:, 0]  # (T, 1) variants written by some converters
    if arr.ndim != len(shape) or any(s not in (-1, n) for s, n in zip(shape, arr.shape)):
        raise SceneValidationError(f"{path}: expected shape {shape}, got {arr.shape}")
    return arr


def _int(value: Any, path: str) -> int:
    kind = type(value)
    if kind is int:  # fast path: most ids and indices
        out = value
    else:
        try:
            if kind is not str and (isinstance(value, (bool, np.bool_))
                                    or not isinstance(value, (int, str, np.integer))):
                raise ValueError
            out = int(value)  # ScenarioNet stores some ids as decimal strings
        except (TypeError, ValueError, OverflowError):
            raise SceneValidationError(f"{path}: expected an integer, got {_describe(value)}") \
                from None
    if not _INT64[0] <= out <= _INT64[1]:
        raise SceneValidationError(f"{path}: integer {_describe(out)} out of range (64-bit)")
    return out


def _float(value: Any, path: str) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        raise SceneValidationError(f"{path}: expected a number, got {_describe(value)}")
    try:
        out = float(value)
    except OverflowError:
        raise SceneValidationError(f"{path}: number {_describe(value)} out of range") from None
    if not np.isfinite(out):
        raise SceneValidationError(f"{path}: expected a finite number, got {out}")
    return out


def _default(value: Any, default: Any) -> Any:
    """``default`` for None (as ``value or default`` did, without truth-testing arrays)."""
    return default if value is None else value


def _bool(value: Any, path: str) -> bool:
    if not isinstance(value, (bool, int, np.bool_, np.integer)):
        raise SceneValidationError(f"{path}: expected a bool, got {_describe(value)}")
    return bool(value)


def _seq(value: Any, path: str) -> list:
    """The items of a list-like field (None: empty)."""
    if value is None:
        return []
    if isinstance(value, np.ndarray):
        if value.ndim != 1:
            raise SceneValidationError(f"{path}: expected a list, got an array of shape "
                                       f"{value.shape}")
        _charge(_PER_ITEM * len(value), path)
        return value.tolist()
    if not isinstance(value, (list, tuple)):
        raise SceneValidationError(f"{path}: expected a list, got {_describe(value)}")
    _charge(_PER_ITEM * len(value), path)
    return list(value)


def _text(value: Any, path: str) -> str:
    if isinstance(value, bool) or not isinstance(value, (str, int, np.integer)):
        raise SceneValidationError(f"{path}: expected a string, got {_describe(value)}")
    return str(value)


def _enum(value: Any, table: dict, path: str):
    try:
        return table[value]
    except (KeyError, TypeError):
        if not isinstance(value, (str, int, type(None))):
            raise SceneValidationError(f"{path}: expected a type name, got {_describe(value)}") \
                from None
        raise SceneValidationError(f"{path}: unknown type {_describe(value)}") from None


def scene_from_scenarionet(sd: Any, budget: int | None = None) -> Scene:
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

    :param budget: bytes of memory the scene may take (None: unlimited); exceeding it is a
        :class:`SceneValidationError` raised before the memory is allocated.
    """
    token = _BUDGET.set(None if budget is None else [budget, budget])
    try:
        return _scene(sd)
    finally:
        _BUDGET.reset(token)


def _decimal(text: str) -> bool:
    try:
        int(text)
    except ValueError:
        return False
    return True


def _key_int(key: Any, path: str) -> int:
    if type(key) is str and 0 < len(key) < 19 and key.isdigit() and key.isascii():
        return int(key)  # fast path: the decimal keys of real files (always within int64)
    return _int(key, f"{path}[{_describe(key)}] key")


class _Ids:
    """Integer ids of a dict's keys: the keys themselves when every key is an integer (or a
    decimal string), else 0..n-1 in recorded order with the original keys kept as names."""

    def __init__(self, keys: list, path: str) -> None:
        self.names: list[str] | None = None
        try:
            self.ids = [_key_int(k, path) for k in keys]
            return
        except SceneValidationError:
            if not any(type(k) is str and not _decimal(k) for k in keys):
                raise  # a bad integer key (a float, a bool, out of range): refused as before
        self.names = [_text(k, f"{path}[{_describe(k)}] key") for k in keys]
        self.ids = list(range(len(keys)))
        self.by_name = {name: i for i, name in enumerate(self.names)}

    @property
    def renumbered(self) -> bool:
        return self.names is not None

    def pairs(self) -> tuple[tuple[int, str], ...]:
        return tuple(enumerate(self.names)) if self.names is not None else ()

    def resolve(self, value: Any, path: str) -> tuple[int | None, str]:
        """``(our id or None when the source's id is unknown, the id as in the source)``."""
        if self.names is None:
            v = _int(value, path)
            return v, str(v)
        name = _text(value, path)
        return self.by_name.get(name), name


def _scene(sd: Any) -> Scene:
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
        length = _int(sd["length"], "length")
    elif ts_raw is not None:
        length = len(_seq(ts_raw, ts_path))
    else:
        raise SceneValidationError("missing key 'length' (and no 'ts' to take it from)")
    if length < 0:
        raise SceneValidationError(f"length: {length} is negative")
    if ts_raw is not None:
        ts = _array(ts_raw, (length,), np.float64, ts_path)
    else:
        ts = np.arange(length) * 0.1
        notes.append("no timestamps (metadata.ts): 0.1 s steps assumed")
    tracks_d = _get(sd, "tracks", "")
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
    sid = meta["scenario_id"] if "scenario_id" in meta else _get(sd, "id", "")
    predictions = []
    for k, v in ttp.items():
        p = f"metadata.tracks_to_predict[{_describe(k)}]"
        predictions.append(RequiredPrediction(
            _int(_get(v, "track_index", p), p + ".track_index"),
            _int(v.get("difficulty", 0), p + ".difficulty")))
    dropped: list[DroppedReference] = []
    interest = []
    for v in _seq(meta.get("objects_of_interest"), "metadata.objects_of_interest"):
        if not track_ids.renumbered:
            interest.append(_int(v, "metadata.objects_of_interest"))
            continue
        name = _text(v, "metadata.objects_of_interest")
        if name in index_of:
            interest.append(index_of[name])
        else:
            dropped.append(DroppedReference(-1, "objects_of_interest", name))
    roadmap, feature_ids = _roadmap(_get(sd, "map_features", ""), dropped)
    signals = _signals(_get(sd, "dynamic_map_states", ""), length, feature_ids, dropped, notes)
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
    return Scene(
        scenario_id=_text(sid, "metadata.scenario_id"),
        timestamps=ts,
        tracks=tracks,
        roadmap=roadmap,
        signals=signals,
        sdc_track_index=sdc_index,
        current_time_index=_int(meta.get("current_time_index", 0), "metadata.current_time_index"),
        tracks_to_predict=tuple(predictions),
        objects_of_interest=tuple(interest),
        source_ids=SourceIds(track_ids.pairs(), feature_ids.pairs()),
        data_quality=DataQuality(tuple(dropped), successors, neighbors, tuple(notes)),
    )


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
        return _int(meta["sdc_track_index"], "metadata.sdc_track_index")
    for value, path in ((meta.get("sdc_id"), "metadata.sdc_id"), (sd.get("sdc_id"), "sdc_id"),
                        (sd.get("sdc_track_index"), "sdc_track_index")):
        if value is None:
            continue
        key = _text(value, path)
        if key in index_of:
            return index_of[key]
        if path == "sdc_track_index":
            return _int(value, path)
        return -1  # an sdc id that is not a track (as before: no sdc)
    return -1


def _tracks(tracks_d: dict, length: int) -> tuple[Tracks, _Ids]:
    n = len(tracks_d)
    _charge(_PER_ITEM * n * length, "tracks")
    cols: dict[str, np.ndarray] = {k: np.zeros((n, length), np.float64) for k in ("x", "y", "z")}
    cols.update({k: np.zeros((n, length), np.float32)
                 for k in ("length", "width", "height", "heading", "vx", "vy")})
    valid = np.zeros((n, length), bool)
    types = np.zeros(n, np.int8)
    keys = list(tracks_d)
    track_ids = _Ids(keys, "tracks")
    for i, key in enumerate(keys):
        obj = tracks_d[key]
        path = f"tracks[{_describe(key)}]"
        types[i] = _enum(_get(obj, "type", path), _OBJECT_TYPES, path + ".type")
        state = _get(obj, "state", path)
        sp = path + ".state"
        pos = _array(_get(state, "position", sp), (length, -1), np.float64, sp + ".position")
        if pos.shape[1] not in (2, 3):
            raise SceneValidationError(f"{sp}.position: expected 2 or 3 columns, got {pos.shape[1]}")
        cols["x"][i], cols["y"][i] = pos[:, 0], pos[:, 1]
        if pos.shape[1] == 3:
            cols["z"][i] = pos[:, 2]
        if isinstance(state, dict) and "size" in state and "length" not in state:
            size = _array(state["size"], (length, -1), np.float32, sp + ".size")  # older layout
            if size.shape[1] not in (2, 3):
                raise SceneValidationError(f"{sp}.size: expected 2 or 3 columns (length, width, "
                                           f"height), got {size.shape[1]}")
            cols["length"][i], cols["width"][i] = size[:, 0], size[:, 1]
            if size.shape[1] == 3:
                cols["height"][i] = size[:, 2]
        else:
            for name in ("length", "width", "height"):
                if name in state:
                    cols[name][i] = _array(state[name], (length,), np.float32, f"{sp}.{name}")
        cols["heading"][i] = _array(_get(state, "heading", sp), (length,), np.float32, sp + ".heading")
        if "velocity" in state:
            vel = _array(state["velocity"], (length, 2), np.float32, sp + ".velocity")
            cols["vx"][i], cols["vy"][i] = vel[:, 0], vel[:, 1]
        valid[i] = _array(_get(state, "valid", sp), (length,), bool, sp + ".valid")
    return Tracks(id=np.array(track_ids.ids, np.int64), type=types, valid=valid, **cols), track_ids


def _points(value: Any, path: str) -> np.ndarray:
    arr = _array(value, (-1, -1), np.float64, path)
    _charge(2 * 24 * arr.shape[0], path)
    if arr.shape[1] == 2:
        arr = np.concatenate([arr, np.zeros((arr.shape[0], 1))], axis=1)
    elif arr.shape[1] != 3:
        raise SceneValidationError(f"{path}: expected 2 or 3 columns, got {arr.shape[1]}")
    return arr


class _Refs:
    """Resolves a map's references; one to an id not in the map is dropped and recorded."""

    def __init__(self, ids: _Ids, lane_ids: set[int], all_ids: set[int],
                 dropped: list[DroppedReference]) -> None:
        self.ids, self.lane_ids, self.all_ids, self.dropped = ids, lane_ids, all_ids, dropped

    def __call__(self, value: Any, owner: int, field: str, path: str,
                 lanes_only: bool = True) -> int | None:
        if self.ids.names is None:  # fast path: integer ids
            fid: int | None = value if type(value) is int else _int(value, path)
            name = None
        else:
            fid, name = self.ids.resolve(value, path)
        if fid is None or fid not in (self.lane_ids if lanes_only else self.all_ids):
            self.dropped.append(DroppedReference(owner, field, str(fid) if name is None else name))
            return None
        return fid

    def lanes(self, items: Any, owner: int, field: str, path: str) -> tuple[int, ...]:
        out = (self(v, owner, field, path) for v in _seq(items, path))
        return tuple(v for v in out if v is not None)


def _segments(items: Any, path: str, refs: _Refs, owner: int, field: str,
              check: bool = True) -> tuple[BoundarySegment, ...]:
    """Boundary segments; ``check=False`` (a neighbour's boundaries, where 0 means unset) keeps
    unknown integer ids as recorded."""
    out = []
    for j, seg in enumerate(_seq(items, path)):
        p = f"{path}[{j}]"
        raw = _get(seg, "boundary_feature_id", p)
        if check or refs.ids.renumbered:
            fid = refs(raw, owner, field, p + ".boundary_feature_id", lanes_only=False)
            if fid is None:
                continue
        else:
            fid = _int(raw, p + ".boundary_feature_id")
        out.append(BoundarySegment(
            _int(_get(seg, "lane_start_index", p), p + ".lane_start_index"),
            _int(_get(seg, "lane_end_index", p), p + ".lane_end_index"),
            fid,
            _enum(seg.get("boundary_type", "UNKNOWN"), _BOUNDARY_TYPES, p + ".boundary_type"),
        ))
    return tuple(out)


def _neighbors(items: Any, path: str, refs: _Refs, owner: int,
               field: str) -> tuple[LaneNeighbor, ...]:
    out = []
    bfield = field + ".boundaries"
    for j, nb in enumerate(_seq(items, path)):
        p = f"{path}[{j}]"
        fid = refs(_get(nb, "feature_id", p), owner, field, p + ".feature_id")
        if fid is None:
            continue
        indices = [_int(_get(nb, k, p), f"{p}.{k}") for k in
                   ("self_start_index", "self_end_index", "neighbor_start_index",
                    "neighbor_end_index")]
        out.append(LaneNeighbor(fid, *indices, boundaries=_segments(
            nb.get("boundaries"), p + ".boundaries", refs, owner, bfield, check=False)))
    return tuple(out)


def _speed_mph(f: dict, path: str) -> float:
    if f.get("speed_limit_mph") is not None:
        return _float(f["speed_limit_mph"], path + ".speed_limit_mph")
    if f.get("speed_limit_kmh") is not None:  # nuScenes and other non-WOMD datasets
        return _float(f["speed_limit_kmh"], path + ".speed_limit_kmh") / _KMH_PER_MPH
    return 0.0


def _roadmap(features: Any, dropped: list[DroppedReference]) -> tuple[RoadMap, _Ids]:
    if not isinstance(features, dict):
        raise SceneValidationError("map_features: expected a dict")
    kinds: dict[str, list] = {k: [] for k in ("lanes", "road_lines", "road_edges", "stop_signs",
                                              "crosswalks", "speed_bumps", "driveways")}
    keys = list(features)
    ids = _Ids(keys, "map_features")
    ftypes = []
    for key in keys:
        path = f"map_features[{_describe(key)}]"
        ftype = _get(features[key], "type", path)
        if not isinstance(ftype, str):
            raise SceneValidationError(f"{path}.type: expected a string, got {_describe(ftype)}")
        ftypes.append(_FEATURE_ALIASES.get(ftype, ftype))
    lane_ids = {fid for fid, t in zip(ids.ids, ftypes) if t in _LANE_TYPES}
    refs = _Refs(ids, lane_ids, set(ids.ids), dropped)
    for key, fid, ftype in zip(keys, ids.ids, ftypes):
        f = features[key]
        path = f"map_features[{_describe(key)}]"
        if ftype in _LANE_TYPES:
            kinds["lanes"].append(Lane(
                id=fid, polyline=_points(_get(f, "polyline", path), path + ".polyline"),
                type=_LANE_TYPES[ftype],
                speed_limit_mph=_speed_mph(f, path),
                interpolating=_bool(f.get("interpolating", False), path + ".interpolating"),
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
            kinds["road_lines"].append(RoadLine(fid, _points(_get(f, "polyline", path),
                                                             path + ".polyline"), _LINE_TYPES[ftype]))
        elif ftype in _EDGE_TYPES:
            kinds["road_edges"].append(RoadEdge(fid, _points(_get(f, "polyline", path),
                                                             path + ".polyline"), _EDGE_TYPES[ftype]))
        elif ftype == schema.STOP_SIGN:
            pos = _array(_get(f, "position", path), (-1,), np.float64, path + ".position")
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
            points = (_points(outline, path + ".polygon") if outline is not None
                      else np.zeros((0, 3)))
            kinds[kind].append(cls(fid, points))
        else:
            raise SceneValidationError(f"{path}: unsupported map feature type {ftype!r}")
    return RoadMap(**{k: tuple(v) for k, v in kinds.items()}), ids


def _int_array(value: Any, length: int, path: str) -> np.ndarray:
    """(length,) int64 of whole numbers within 64 bits (floats are accepted when integral)."""
    arr = _array(value, (length,), np.float64, path) if not (
        isinstance(value, np.ndarray) and value.dtype.kind in "iub") else \
        _array(value, (length,), np.int64, path)
    if arr.dtype.kind == "f":
        bad = ~np.isfinite(arr) | (arr != np.round(arr)) | (np.abs(arr) >= 2.0 ** 63)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise SceneValidationError(f"{path}[{k}]: expected an integer, got {float(arr[k]):.6g}")
        arr = arr.astype(np.int64)
    return arr


def _signal_state(value: Any, path: str) -> int:
    """A signal state: a ``LANE_STATE_*`` name, or the older layout's integer WOMD
    ``TrafficSignalLaneState`` code (0 unknown .. 8 flashing caution; same values as ours)."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)):
        if not 0 <= value <= max(SignalState):
            raise SceneValidationError(f"{path}: unknown signal state code {_describe(value)}")
        return int(value)
    return _enum(value, _SIGNAL_STATES, path)


def _signals(dyn: Any, length: int, map_ids: _Ids, dropped: list[DroppedReference],
             notes: list[str]) -> SignalStates:
    if not isinstance(dyn, dict):
        raise SceneValidationError("dynamic_map_states: expected a dict")
    _charge(_PER_ITEM * length, "dynamic_map_states")
    per_step: list[list[tuple[int, int, np.ndarray]]] = [[] for _ in range(length)]
    older_steps: set[int] = set()

    def lane_id(value: Any, path: str) -> int | None:
        fid, name = map_ids.resolve(value, path)
        if fid is None:  # only for a map with named features (integer ids are kept as recorded)
            dropped.append(DroppedReference(-1, "dynamic_map_states.lane", name))
        return fid

    for key, light in dyn.items():
        path = f"dynamic_map_states[{_describe(key)}]"
        if not isinstance(light, dict):
            raise SceneValidationError(f"{path}: expected a dict, got {type(light).__name__}")
        state = _get(light, "state", path)
        sp = path + ".state"
        if isinstance(state, dict) and "lane" in state and "lane" not in light:
            # older MetaDrive layout: per-step lane ids (0 = no record) and stop points
            lanes = _int_array(state["lane"], length, sp + ".lane")
            codes = _int_array(_get(state, "object_state", sp), length, sp + ".object_state")
            stops = _array(_get(state, "stop_point", sp), (length, -1), np.float64,
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
        states = _seq(_get(state, "object_state", sp), sp + ".object_state")
        if len(states) != length:
            raise SceneValidationError(
                f"{path}.state.object_state: expected {length} steps, got {len(states)}")
        stop = _array(light.get("stop_point", np.zeros(3)), (-1,), np.float64, path + ".stop_point")
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

def load_scenarionet(path: str | PathLike) -> Scene:
    """Load and validate one ScenarioNet pickle (restricted unpickler).

    :raises SceneFormatError: naming the file and the problem (one line).
    """
    p = Path(path)
    with open_regular(p) as fh:  # SceneFormatError for a FIFO, device, loop...; OSError
        data = fh.read()
    try:
        sd = safe_loads(data)
    except UnsafePickleError as exc:
        raise SceneFormatError(p, 0, f"unsafe pickle, nothing executed: "
                                     f"{printable(str(exc), 300)}") from None
    except Exception as exc:  # LOAD_ERRORS, or anything else a malformed file provokes
        raise SceneFormatError(p, 0, f"unreadable pickle ({_reason(exc)})") from None
    try:
        scene = scene_from_scenarionet(sd, allocation_budget(len(data)))
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
    mapping = _default(load(MAPPING_FILE), {}) if (root / MAPPING_FILE).exists() else {}
    if not isinstance(summary, dict) or not isinstance(mapping, dict):
        raise SceneFormatError(root, None, "dataset summary/mapping is not a dict")
    files = []
    for name in summary:
        sub = mapping.get(name, "")
        if not isinstance(name, str) or not isinstance(sub, str) or name in ("", ".", "..") \
                or "/" in name or "\\" in name or "\0" in name + sub or Path(sub).is_absolute() \
                or ".." in Path(sub).parts:
            raise SceneFormatError(root / SUMMARY_FILE, None,
                                   f"bad scenario file name {_describe(name)} "
                                   f"(folder {_describe(sub)})")
        files.append(root / sub / name)
    return files


def iter_scenarionet(path: str | PathLike) -> Iterator[tuple[int, Scene | SceneFormatError]]:
    """Yield ``(index, Scene or SceneFormatError)`` for a pickle or a dataset folder."""
    p = Path(path)
    files = dataset_files(p) if p.is_dir() else [p]
    for i, f in enumerate(files):
        try:
            yield i, load_scenarionet(f)
        except SceneFormatError as exc:
            yield i, exc
        except OSError as exc:
            yield i, SceneFormatError(f, None, f"cannot read ({exc.strerror or exc})")
