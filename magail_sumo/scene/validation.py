"""Semantic checks of a Scene: what a reader must refuse rather than pass on or "fix"."""

from __future__ import annotations

import numpy as np

from .roadmap import FEATURE_KINDS, Lane
from .scene import Scene
from .types import ObjectType

#: Largest accepted magnitude of a coordinate (metres, scene frame): 10,000 km, beyond any local
#: or UTM frame a dataset uses. Larger finite values (1e308) are refused as out of range: they
#: overflow every distance computed from them.
MAX_COORDINATE = 1e7
#: How far (metres) a map point may lie outside the bounding box of the scene's valid object
#: states. Real WOMD / ScenarioNet maps reach about 150 m beyond it; a map reaching 10 km
#: further is not a recording of this scene (one lane point at x = 1e9 made ``convert`` build
#: a road network of gigabytes) and the scene is refused, naming the feature.
MAP_MARGIN = 10_000.0


class SceneValidationError(ValueError):
    """A scene breaks an invariant; the message names the element and the problem."""


def _number(value: float) -> str:
    return f"{value:.6g}"


def validate_scene(scene: Scene) -> None:
    """Raise :class:`SceneValidationError` on the first problem found.

    Checks: at least one time step and strictly increasing timestamps; at least one track and
    at least one valid object state; unique track ids; known object types; finite numbers in
    every track state, timestamp, map point and stop point; coordinates of magnitude at most
    :data:`MAX_COORDINATE`; box length and width > 0 and height >= 0 on valid states; map
    points and stop points within :data:`MAP_MARGIN` of the bounding box of the valid states;
    unique map feature ids; lane references (entry/exit lanes, neighbours, boundaries,
    stop-sign lanes) that exist; indices (sdc, current time, tracks to predict) in range;
    objects of interest that exist; original (source) ids of existing tracks / features, each
    given once.
    """
    tr = scene.tracks
    if tr.num_tracks == 0:
        raise SceneValidationError("scene has zero tracks")
    ids, counts = np.unique(tr.id, return_counts=True)
    if np.any(counts > 1):
        raise SceneValidationError(f"duplicate track id {int(ids[counts > 1][0])}")
    bad_type = (tr.type < ObjectType.UNSET) | (tr.type > ObjectType.OTHER)
    if np.any(bad_type):
        i = int(np.flatnonzero(bad_type)[0])
        raise SceneValidationError(f"track {int(tr.id[i])}: unknown object type {int(tr.type[i])}")
    ts = scene.timestamps
    if ts.shape[0] == 0:
        raise SceneValidationError("scene has zero time steps")
    if not np.all(np.isfinite(ts)):
        raise SceneValidationError("timestamps contain NaN or inf")
    if ts.shape[0] > 1:
        back = np.diff(ts) <= 0
        if np.any(back):
            t = int(np.flatnonzero(back)[0])
            raise SceneValidationError(
                f"timestamps not strictly increasing: step {t + 1} at {_number(ts[t + 1])} s "
                f"follows {_number(ts[t])} s")
    for name in ("x", "y", "z", "length", "width", "height", "heading", "vx", "vy"):
        arr = getattr(tr, name)
        bad = ~np.isfinite(arr)
        if name in ("x", "y", "z"):
            bad |= np.abs(arr) > MAX_COORDINATE
        if np.any(bad):
            i, t = (int(v[0]) for v in np.nonzero(bad))
            value = float(arr[i, t])
            what = (f"out of range (|{name}| > {MAX_COORDINATE:g} m)" if np.isfinite(value)
                    else "not finite")
            raise SceneValidationError(
                f"track {int(tr.id[i])} step {t}: field {name} is {_number(value)}, {what}"
            )
    valid = tr.valid
    if not valid.any():
        raise SceneValidationError("no track has a valid state (nothing usable in the scene)")
    for name, lowest in (("length", "positive"), ("width", "positive"), ("height", "non-negative")):
        arr = getattr(tr, name)
        bad = valid & ((arr <= 0) if lowest == "positive" else (arr < 0))
        if np.any(bad):
            i, t = (int(v[0]) for v in np.nonzero(bad))
            raise SceneValidationError(
                f"track {int(tr.id[i])} step {t}: box {name} {_number(float(arr[i, t]))} on a "
                f"valid state (must be {lowest})"
            )
    _check_map(scene)
    sig = scene.signals
    if len(sig):
        if not np.all(np.isfinite(sig.stop_point)):
            k = int(np.flatnonzero(~np.isfinite(sig.stop_point).all(axis=1))[0])
            raise SceneValidationError(
                f"signal state of lane {int(sig.lane[k])} at step {int(sig.step[k])}: "
                "stop_point is not finite"
            )
        k = _far_point(sig.stop_point, *_extent(scene))
        if k is not None:
            raise SceneValidationError(
                f"signal state of lane {int(sig.lane[k])} at step {int(sig.step[k])}: stop_point "
                f"{_where(sig.stop_point[k])} is far outside the scene (more than "
                f"{MAP_MARGIN:g} m from the bounding box of the valid object states)"
            )
        if sig.step.min() < 0 or sig.step.max() >= scene.num_steps:
            raise SceneValidationError(f"signal state step out of range 0..{scene.num_steps - 1}")
    n = tr.num_tracks
    if not -1 <= scene.sdc_track_index < n:
        raise SceneValidationError(f"sdc_track_index {scene.sdc_track_index} out of range (0..{n - 1})")
    if scene.num_steps and not 0 <= scene.current_time_index < scene.num_steps:
        raise SceneValidationError(
            f"current_time_index {scene.current_time_index} out of range (0..{scene.num_steps - 1})"
        )
    for req in scene.tracks_to_predict:
        if not 0 <= req.track_index < n:
            raise SceneValidationError(f"tracks_to_predict index {req.track_index} out of range (0..{n - 1})")
    known = set(int(i) for i in tr.id)
    for oid in scene.objects_of_interest:
        if oid not in known:
            raise SceneValidationError(f"objects_of_interest id {oid} is not a track id")
    _check_source_ids(scene.source_ids.tracks, known, "track")
    if scene.source_ids.map_features:
        _check_source_ids(scene.source_ids.map_features,
                          {f.id for kind in FEATURE_KINDS for f in scene.roadmap.features(kind)},
                          "map feature")


def _check_source_ids(pairs: tuple[tuple[int, str], ...], known: set[int], what: str) -> None:
    """Original ids: one per existing id, each name once (the writer writes them as keys)."""
    ids = [i for i, _ in pairs]
    names = [n for _, n in pairs]
    if len(set(ids)) != len(ids) or len(set(names)) != len(names):
        raise SceneValidationError(f"source ids: a {what} id or original id appears twice")
    unknown = set(ids) - known
    if unknown:
        raise SceneValidationError(f"source ids: {what} id {min(unknown)} does not exist")


def _extent(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) corners (x, y) of the box :data:`MAP_MARGIN` around the valid object states."""
    tr = scene.tracks
    x, y = tr.x[tr.valid], tr.y[tr.valid]
    return (np.array([x.min(), y.min()]) - MAP_MARGIN, np.array([x.max(), y.max()]) + MAP_MARGIN)


def _far_point(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> int | None:
    """Index of the first of ``points`` (K, >=2) outside the box ``lo..hi``, or None."""
    if points.shape[0] == 0:
        return None
    x, y = points[:, 0], points[:, 1]  # column reductions: much faster than axis=0 on (K, 3)
    if x.min() >= lo[0] and y.min() >= lo[1] and x.max() <= hi[0] and y.max() <= hi[1]:
        return None  # fast path: every point inside
    xy = points[:, :2]
    out = ((xy < lo) | (xy > hi)).any(axis=1)
    return int(np.flatnonzero(out)[0]) if out.any() else None


def _where(point: np.ndarray) -> str:
    return "(" + ", ".join(_number(float(v)) for v in point[:2]) + ")"


def _check_map(scene: Scene) -> None:
    rm = scene.roadmap
    seen: set[int] = set()
    owners: list[tuple[str, int]] = []  # (kind, id) of each block of points
    blocks: list[np.ndarray] = []
    for kind in FEATURE_KINDS:
        for feat in rm.features(kind):
            if feat.id in seen:
                raise SceneValidationError(f"duplicate map feature id {feat.id}")
            seen.add(feat.id)
            points = getattr(feat, "polyline", None)
            if points is None:
                points = getattr(feat, "polygon", None)
            if points is None:
                points = feat.position.reshape(1, 3)
            owners.append((kind, feat.id))
            blocks.append(points)
    if blocks:  # one vectorised pass over every map point; the feature is located on failure
        sizes = np.fromiter((b.shape[0] for b in blocks), np.int64, len(blocks))
        allpts = np.concatenate(blocks)
        if not np.isfinite(allpts).all():
            finite = np.isfinite(allpts).all(axis=1)
            kind, fid = owners[_block_of(sizes, int(np.flatnonzero(~finite)[0]))]
            raise SceneValidationError(f"{kind} {fid}: coordinates contain NaN or inf")
        k = _far_point(allpts, *_extent(scene))
        if k is not None:
            kind, fid = owners[_block_of(sizes, k)]
            raise SceneValidationError(
                f"{kind} {fid}: point {_where(allpts[k])} is far outside the scene (more than "
                f"{MAP_MARGIN:g} m from the bounding box of the valid object states)")
    lane_ids = {lane.id for lane in rm.lanes}
    for lane in rm.lanes:
        _check_lane_refs(lane, lane_ids, seen)
    for sign in rm.stop_signs:
        for lid in sign.lanes:
            if lid not in lane_ids:
                raise SceneValidationError(f"stop_sign {sign.id}: controlled lane {lid} does not exist")


def _block_of(sizes: np.ndarray, k: int) -> int:
    """Index of the block holding row ``k`` of the concatenation of blocks of ``sizes`` rows."""
    return int(np.searchsorted(np.cumsum(sizes), k, side="right"))


def _check_lane_refs(lane: Lane, lane_ids: set[int], feature_ids: set[int]) -> None:
    n = lane.polyline.shape[0]
    for name in ("entry_lanes", "exit_lanes"):
        for lid in getattr(lane, name):
            if lid not in lane_ids:
                raise SceneValidationError(f"lane {lane.id}: {name[:-1]} {lid} does not exist")
    for name in ("left_neighbors", "right_neighbors"):
        for nb in getattr(lane, name):
            if nb.feature_id not in lane_ids:
                raise SceneValidationError(f"lane {lane.id}: {name[:-1]} {nb.feature_id} does not exist")
    for name in ("left_boundaries", "right_boundaries"):
        for seg in getattr(lane, name):
            if seg.boundary_feature_id not in feature_ids:
                raise SceneValidationError(
                    f"lane {lane.id}: {name[:-3]}y feature {seg.boundary_feature_id} does not exist"
                )
            if not (0 <= seg.lane_start_index <= seg.lane_end_index < n):
                raise SceneValidationError(
                    f"lane {lane.id}: {name[:-3]}y index range "
                    f"{seg.lane_start_index}..{seg.lane_end_index} outside its {n} points"
                )
