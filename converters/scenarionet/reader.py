"""Read ScenarioNet scenario pickles (``sd_*.pkl``) into :class:`~magail_sumo.scene.Scene`.

Pickles are loaded only through :mod:`converters.scenarionet.safe_pickle`. The dict layout is
the one ScenarioNet's Waymo converter writes (see ``schema.py``); every access is checked and a
wrong shape or type raises an error naming the key path.
"""

from __future__ import annotations

import contextvars
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
from magail_sumo.scene import (
    BoundarySegment, Crosswalk, Driveway, Lane, LaneNeighbor, ObjectType, RequiredPrediction,
    RoadEdge, RoadLine, RoadMap, Scene, SceneValidationError, SignalStates, SpeedBump, StopSign,
    Tracks, validate_scene,
)

SUMMARY_FILE = "dataset_summary.pkl"
MAPPING_FILE = "dataset_mapping.pkl"

_OBJECT_TYPES = schema.inverse(schema.OBJECT_TYPES)
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

    :param budget: bytes of memory the scene may take (None: unlimited); exceeding it is a
        :class:`SceneValidationError` raised before the memory is allocated.
    """
    token = _BUDGET.set(None if budget is None else [budget, budget])
    try:
        return _scene(sd)
    finally:
        _BUDGET.reset(token)


def _scene(sd: Any) -> Scene:
    if not isinstance(sd, dict):
        raise SceneValidationError(f"expected a scenario dict, got {type(sd).__name__}")
    length = _int(_get(sd, "length", ""), "length")
    if length < 0:
        raise SceneValidationError(f"length: {length} is negative")
    meta = _get(sd, "metadata", "")
    ts = _array(_get(meta, "ts", "metadata"), (length,), np.float64, "metadata.ts")
    tracks_d = _get(sd, "tracks", "")
    if not isinstance(tracks_d, dict):
        raise SceneValidationError("tracks: expected a dict")
    tracks, index_of = _tracks(tracks_d, length)
    sdc = meta.get("sdc_id")
    sdc_index = meta.get("sdc_track_index")
    if sdc_index is None:
        sdc_index = index_of.get(_text(sdc, "metadata.sdc_id"), -1) if sdc is not None else -1
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
    return Scene(
        scenario_id=_text(sid, "metadata.scenario_id"),
        timestamps=ts,
        tracks=tracks,
        roadmap=_roadmap(_get(sd, "map_features", "")),
        signals=_signals(_get(sd, "dynamic_map_states", ""), length),
        sdc_track_index=_int(sdc_index, "metadata.sdc_track_index"),
        current_time_index=_int(meta.get("current_time_index", 0), "metadata.current_time_index"),
        tracks_to_predict=tuple(predictions),
        objects_of_interest=tuple(
            _int(v, "metadata.objects_of_interest")
            for v in _seq(meta.get("objects_of_interest"), "metadata.objects_of_interest")
        ),
    )


def _tracks(tracks_d: dict, length: int) -> tuple[Tracks, dict[str, int]]:
    n = len(tracks_d)
    _charge(_PER_ITEM * n * length, "tracks")
    cols: dict[str, np.ndarray] = {k: np.zeros((n, length), np.float64) for k in ("x", "y", "z")}
    cols.update({k: np.zeros((n, length), np.float32)
                 for k in ("length", "width", "height", "heading", "vx", "vy")})
    valid = np.zeros((n, length), bool)
    ids = np.zeros(n, np.int64)
    types = np.zeros(n, np.int8)
    index_of: dict[str, int] = {}
    for i, (key, obj) in enumerate(tracks_d.items()):
        path = f"tracks[{_describe(key)}]"
        index_of[_text(key, path + " key")] = i
        ids[i] = _int(key, path + " key")
        types[i] = _enum(_get(obj, "type", path), _OBJECT_TYPES, path + ".type")
        state = _get(obj, "state", path)
        sp = path + ".state"
        pos = _array(_get(state, "position", sp), (length, -1), np.float64, sp + ".position")
        if pos.shape[1] not in (2, 3):
            raise SceneValidationError(f"{sp}.position: expected 2 or 3 columns, got {pos.shape[1]}")
        cols["x"][i], cols["y"][i] = pos[:, 0], pos[:, 1]
        if pos.shape[1] == 3:
            cols["z"][i] = pos[:, 2]
        for name in ("length", "width", "height", "heading"):
            if name in state or name == "heading":
                cols[name][i] = _array(_get(state, name, sp), (length,), np.float32, f"{sp}.{name}")
        if "velocity" in state:
            vel = _array(state["velocity"], (length, 2), np.float32, sp + ".velocity")
            cols["vx"][i], cols["vy"][i] = vel[:, 0], vel[:, 1]
        valid[i] = _array(_get(state, "valid", sp), (length,), bool, sp + ".valid")
    return Tracks(id=ids, type=types, valid=valid, **cols), index_of


def _points(value: Any, path: str) -> np.ndarray:
    arr = _array(value, (-1, -1), np.float64, path)
    _charge(2 * 24 * arr.shape[0], path)
    if arr.shape[1] == 2:
        arr = np.concatenate([arr, np.zeros((arr.shape[0], 1))], axis=1)
    elif arr.shape[1] != 3:
        raise SceneValidationError(f"{path}: expected 2 or 3 columns, got {arr.shape[1]}")
    return arr


def _segments(items: Any, path: str) -> tuple[BoundarySegment, ...]:
    out = []
    for j, seg in enumerate(_seq(items, path)):
        p = f"{path}[{j}]"
        out.append(BoundarySegment(
            _int(_get(seg, "lane_start_index", p), p + ".lane_start_index"),
            _int(_get(seg, "lane_end_index", p), p + ".lane_end_index"),
            _int(_get(seg, "boundary_feature_id", p), p + ".boundary_feature_id"),
            _enum(seg.get("boundary_type", "UNKNOWN"), _BOUNDARY_TYPES, p + ".boundary_type"),
        ))
    return tuple(out)


def _neighbors(items: Any, path: str) -> tuple[LaneNeighbor, ...]:
    out = []
    for j, nb in enumerate(_seq(items, path)):
        p = f"{path}[{j}]"
        indices = [_int(_get(nb, k, p), f"{p}.{k}") for k in
                   ("feature_id", "self_start_index", "self_end_index", "neighbor_start_index",
                    "neighbor_end_index")]
        out.append(LaneNeighbor(*indices,
                                boundaries=_segments(nb.get("boundaries"), p + ".boundaries")))
    return tuple(out)


def _roadmap(features: Any) -> RoadMap:
    if not isinstance(features, dict):
        raise SceneValidationError("map_features: expected a dict")
    kinds: dict[str, list] = {k: [] for k in ("lanes", "road_lines", "road_edges", "stop_signs",
                                              "crosswalks", "speed_bumps", "driveways")}
    for key, f in features.items():
        path = f"map_features[{_describe(key)}]"
        fid = _int(key, path + " key")
        ftype = _get(f, "type", path)
        if not isinstance(ftype, str):
            raise SceneValidationError(f"{path}.type: expected a string, got {_describe(ftype)}")
        if ftype in _LANE_TYPES:
            kinds["lanes"].append(Lane(
                id=fid, polyline=_points(_get(f, "polyline", path), path + ".polyline"),
                type=_LANE_TYPES[ftype],
                speed_limit_mph=_float(_default(f.get("speed_limit_mph"), 0.0),
                                       path + ".speed_limit_mph"),
                interpolating=_bool(f.get("interpolating", False), path + ".interpolating"),
                entry_lanes=tuple(_int(v, path + ".entry_lanes")
                                  for v in _seq(f.get("entry_lanes"), path + ".entry_lanes")),
                exit_lanes=tuple(_int(v, path + ".exit_lanes")
                                 for v in _seq(f.get("exit_lanes"), path + ".exit_lanes")),
                left_neighbors=_neighbors(f.get("left_neighbor"), path + ".left_neighbor"),
                right_neighbors=_neighbors(f.get("right_neighbor"), path + ".right_neighbor"),
                left_boundaries=_segments(f.get("left_boundaries"), path + ".left_boundaries"),
                right_boundaries=_segments(f.get("right_boundaries"), path + ".right_boundaries"),
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
                fid, tuple(_int(v, path + ".lane") for v in _seq(f.get("lane"), path + ".lane")),
                np.pad(pos, (0, 3 - pos.shape[0])) if pos.shape[0] < 3 else pos))
        elif ftype in _AREA_TYPES:
            kind, cls = _AREA_TYPES[ftype]
            kinds[kind].append(cls(fid, _points(_get(f, "polygon", path), path + ".polygon")))
        else:
            raise SceneValidationError(f"{path}: unsupported map feature type {ftype!r}")
    return RoadMap(**{k: tuple(v) for k, v in kinds.items()})


def _signals(dyn: Any, length: int) -> SignalStates:
    if not isinstance(dyn, dict):
        raise SceneValidationError("dynamic_map_states: expected a dict")
    _charge(_PER_ITEM * length, "dynamic_map_states")
    per_step: list[list[tuple[int, int, np.ndarray]]] = [[] for _ in range(length)]
    for key, light in dyn.items():
        path = f"dynamic_map_states[{_describe(key)}]"
        if not isinstance(light, dict):
            raise SceneValidationError(f"{path}: expected a dict, got {type(light).__name__}")
        lane = _int(light.get("lane", key), path + ".lane")
        states = _seq(_get(_get(light, "state", path), "object_state", path + ".state"),
                      path + ".state.object_state")
        if len(states) != length:
            raise SceneValidationError(
                f"{path}.state.object_state: expected {length} steps, got {len(states)}")
        stop = _array(light.get("stop_point", np.zeros(3)), (-1,), np.float64, path + ".stop_point")
        stop = np.pad(stop, (0, 3 - stop.shape[0])) if stop.shape[0] < 3 else stop[:3]
        for t, s in enumerate(states):
            if s is not None:
                per_step[t].append((lane, _enum(s, _SIGNAL_STATES, f"{path}.state[{t}]"), stop))
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
