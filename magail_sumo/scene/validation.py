"""Semantic checks of a Scene: what a reader must refuse rather than pass on or "fix"."""

from __future__ import annotations

import numpy as np

from .roadmap import FEATURE_KINDS, Lane
from .scene import Scene
from .types import ObjectType


class SceneValidationError(ValueError):
    """A scene breaks an invariant; the message names the element and the problem."""


def validate_scene(scene: Scene) -> None:
    """Raise :class:`SceneValidationError` on the first problem found.

    Checks: at least one track; unique track ids; known object types; finite numbers in
    every track state, timestamp, map point and stop point; unique map feature ids; lane
    references (entry/exit lanes, neighbours, boundaries, stop-sign lanes) that exist;
    indices (sdc, current time, tracks to predict) in range; objects of interest that exist.
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
    if not np.all(np.isfinite(scene.timestamps)):
        raise SceneValidationError("timestamps contain NaN or inf")
    for name in ("x", "y", "z", "length", "width", "height", "heading", "vx", "vy"):
        arr = getattr(tr, name)
        bad = ~np.isfinite(arr)
        if np.any(bad):
            i, t = (int(v[0]) for v in np.nonzero(bad))
            raise SceneValidationError(
                f"track {int(tr.id[i])} step {t}: field {name} is {float(arr[i, t])}"
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


def _check_map(scene: Scene) -> None:
    rm = scene.roadmap
    seen: set[int] = set()
    for kind in FEATURE_KINDS:
        for feat in rm.features(kind):
            if feat.id in seen:
                raise SceneValidationError(f"duplicate map feature id {feat.id}")
            seen.add(feat.id)
            points = getattr(feat, "polyline", None)
            if points is None:
                points = getattr(feat, "polygon", None)
            if points is None:
                points = feat.position
            if not np.all(np.isfinite(points)):
                raise SceneValidationError(f"{kind} {feat.id}: coordinates contain NaN or inf")
    lane_ids = {lane.id for lane in rm.lanes}
    for lane in rm.lanes:
        _check_lane_refs(lane, lane_ids, seen)
    for sign in rm.stop_signs:
        for lid in sign.lanes:
            if lid not in lane_ids:
                raise SceneValidationError(f"stop_sign {sign.id}: controlled lane {lid} does not exist")


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
                    f"lane {lane.id}: {name[:-2]}y feature {seg.boundary_feature_id} does not exist"
                )
            if not (0 <= seg.lane_start_index <= seg.lane_end_index < n):
                raise SceneValidationError(
                    f"lane {lane.id}: {name[:-2]}y index range "
                    f"{seg.lane_start_index}..{seg.lane_end_index} outside its {n} points"
                )
