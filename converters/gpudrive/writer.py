"""A :class:`~magail_sumo.scene.Scene` as a GPUDrive JSON scene (:mod:`.reader`'s layout), so a
scene read from any source can be handed to GPUDrive / PufferDrive tools and read back.

What the format cannot hold is lost on the way and reported by the reader when read back: lane
connectivity (inferred again from the geometry), speed limits, the lanes a stop sign controls,
per-step box sizes (the median over the valid steps is written).
"""

from __future__ import annotations

from os import PathLike
from pathlib import Path

import numpy as np

from magail_sumo.outputs import write_text
from magail_sumo.scene import ObjectType, Scene, SignalState

from .reader import ROAD_EDGE_OFFSET, ROAD_LINE_OFFSET

_TYPE_NAMES = {ObjectType.VEHICLE: "vehicle", ObjectType.PEDESTRIAN: "pedestrian",
               ObjectType.CYCLIST: "cyclist", ObjectType.OTHER: "other",
               ObjectType.UNSET: "unset"}
#: GPUDrive MapElementIds of the area features and stop signs
_STOP_SIGN, _CROSSWALK, _SPEED_BUMP, _DRIVEWAY = 17, 18, 19, 20


def _pts(a: np.ndarray) -> list[dict[str, float]]:
    return [{"x": float(p[0]), "y": float(p[1]), "z": float(p[2]) if len(p) > 2 else 0.0}
            for p in np.asarray(a)]


def _median(values: np.ndarray, valid: np.ndarray) -> float:
    return float(np.median(values[valid])) if valid.any() else float(values[0])


def scene_to_gpudrive(scene: Scene) -> dict:
    """The JSON document of ``scene`` (module doc)."""
    tr = scene.tracks
    objects = []
    for i in range(tr.num_tracks):
        v = tr.valid[i]
        objects.append({
            "id": int(tr.id[i]), "type": _TYPE_NAMES.get(ObjectType(int(tr.type[i])), "other"),
            "position": [{"x": float(x), "y": float(y), "z": float(z)}
                         for x, y, z in zip(tr.x[i], tr.y[i], tr.z[i])],
            "heading": [float(h) for h in tr.heading[i]],
            "velocity": [{"x": float(x), "y": float(y)} for x, y in zip(tr.vx[i], tr.vy[i])],
            "valid": [bool(b) for b in v],
            "length": _median(tr.length[i], v), "width": _median(tr.width[i], v),
            "height": _median(tr.height[i], v),
            "goalPosition": _pts([[tr.x[i, np.flatnonzero(v)[-1]], tr.y[i, np.flatnonzero(v)[-1]],
                                   tr.z[i, np.flatnonzero(v)[-1]]]])[0] if v.any() else None,
            "mark_as_expert": False})
    rm = scene.roadmap
    roads = [{"id": l.id, "type": "lane", "map_element_id": int(l.type),
              "geometry": _pts(l.polyline)} for l in rm.lanes]
    roads += [{"id": l.id, "type": "road_line", "map_element_id": int(l.type) + ROAD_LINE_OFFSET,
               "geometry": _pts(l.polyline)} for l in rm.road_lines]
    roads += [{"id": e.id, "type": "road_edge", "map_element_id": int(e.type) + ROAD_EDGE_OFFSET,
               "geometry": _pts(e.polyline)} for e in rm.road_edges]
    roads += [{"id": s.id, "type": "stop_sign", "map_element_id": _STOP_SIGN,
               "geometry": _pts([s.position])} for s in rm.stop_signs]
    for kind, code, feats in (("crosswalk", _CROSSWALK, rm.crosswalks),
                              ("speed_bump", _SPEED_BUMP, rm.speed_bumps),
                              ("driveway", _DRIVEWAY, rm.driveways)):
        roads += [{"id": f.id, "type": kind, "map_element_id": code,
                   "geometry": _pts(f.polygon)} for f in feats]
    tl: dict[str, dict] = {}
    sig = scene.signals
    for lane in sorted(set(np.asarray(sig.lane).tolist())):
        rows = np.flatnonzero(np.asarray(sig.lane) == lane)
        state: list[str | None] = [None] * scene.num_steps
        xs: list[float | None] = [None] * scene.num_steps
        ys: list[float | None] = [None] * scene.num_steps
        for r in rows:
            k = int(sig.step[r])
            state[k] = "LANE_STATE_" + SignalState(int(sig.state[r])).name
            xs[k], ys[k] = float(sig.stop_point[r][0]), float(sig.stop_point[r][1])
        tl[str(lane)] = {"state": state, "x": xs, "y": ys}
    return {"name": f"{scene.scenario_id}.json", "scenario_id": scene.scenario_id,
            "objects": objects, "roads": roads, "tl_states": tl,
            "metadata": {"sdc_track_index": scene.sdc_track_index,
                         "current_time_index": scene.current_time_index,
                         "objects_of_interest": list(scene.objects_of_interest),
                         "tracks_to_predict": [{"track_index": p.track_index,
                                                "difficulty": int(p.difficulty)}
                                               for p in scene.tracks_to_predict]}}


def write_gpudrive(scene: Scene, path: str | PathLike) -> Path:
    """Write ``scene`` as a GPUDrive JSON file (atomically); returns the path."""
    import json

    return write_text(Path(path), json.dumps(scene_to_gpudrive(scene), allow_nan=False))
