"""Write :class:`~magail_sumo.scene.Scene` objects as ScenarioNet scenario dicts / pickles.

The layout follows ScenarioNet's Waymo converter so ScenarioNet and MetaDrive load the files
(plain dict, str keys, protocol 4, ``sd_<dataset>_<version>_<id>.pkl`` plus
``dataset_summary.pkl`` / ``dataset_mapping.pkl``). One deliberate difference: positions,
polylines, stop points and timestamps are float64 (ScenarioNet uses float32, which rounds WOMD
coordinates by up to ~0.5 mm), so a WOMD -> ScenarioNet -> Scene round trip is exact.
"""

from __future__ import annotations

import collections
import copy
import pickle
from os import PathLike
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from converters.scenarionet import schema
from converters.scenarionet.reader import MAPPING_FILE, SUMMARY_FILE
from magail_sumo.scene import BoundarySegment, LaneNeighbor, ObjectType, Scene

PICKLE_PROTOCOL = 4
DEFAULT_VERSION = "v1.2"


class _Names:
    """The ids to write: the original ids of a source numbered by the reader
    (``Scene.source_ids``), else the integer ids."""

    def __init__(self, scene: Scene) -> None:
        self.tracks = scene.source_ids.track_names()
        self.features = scene.source_ids.feature_names()

    def track(self, tid: int) -> str:
        return self.tracks.get(tid, str(tid))

    def feature(self, fid: int) -> str:
        return self.features.get(fid, str(fid))

    def ref(self, fid: int) -> int | str:
        """A reference to a map feature: an int (as ScenarioNet writes), or the original id."""
        return self.features[fid] if fid in self.features else int(fid)


def _segments(segs: Iterable[BoundarySegment], names: _Names) -> list[dict]:
    return [{"lane_start_index": str(s.lane_start_index), "lane_end_index": str(s.lane_end_index),
             "boundary_type": schema.BOUNDARY_TYPES[s.boundary_type],
             "boundary_feature_id": names.feature(s.boundary_feature_id)} for s in segs]


def _neighbors(nbs: Iterable[LaneNeighbor], names: _Names) -> list[dict]:
    return [{"feature_id": names.feature(n.feature_id), "self_start_index": str(n.self_start_index),
             "self_end_index": str(n.self_end_index),
             "neighbor_start_index": str(n.neighbor_start_index),
             "neighbor_end_index": str(n.neighbor_end_index),
             "boundaries": _segments(n.boundaries, names)} for n in nbs]


def _tracks(scene: Scene, names: _Names) -> dict[str, dict]:
    tr = scene.tracks
    out: dict[str, dict] = {}
    for i in range(tr.num_tracks):
        key = names.track(int(tr.id[i]))
        tname = schema.OBJECT_TYPES[ObjectType(int(tr.type[i]))]
        out[key] = {
            "type": tname,
            "state": {
                "position": np.stack([tr.x[i], tr.y[i], tr.z[i]], axis=1),
                "length": tr.length[i].copy(), "width": tr.width[i].copy(),
                "height": tr.height[i].copy(), "heading": tr.heading[i].copy(),
                "velocity": np.stack([tr.vx[i], tr.vy[i]], axis=1),
                "valid": tr.valid[i].copy(),
            },
            "metadata": {"track_length": scene.num_steps, "type": tname, "object_id": key,
                         "dataset": "waymo"},
        }
    return out


def _map_features(scene: Scene, names: _Names) -> dict[str, dict]:
    rm = scene.roadmap
    out: dict[int, tuple[str, dict]] = {}
    for lane in rm.lanes:
        out[lane.id] = (names.feature(lane.id), {
            "speed_limit_mph": float(lane.speed_limit_mph),
            "speed_limit_kmh": float(lane.speed_limit_mph) * 1.609344,
            "type": schema.LANE_TYPES[lane.type],
            "polyline": lane.polyline.copy(),
            "interpolating": bool(lane.interpolating),
            "entry_lanes": [names.ref(v) for v in lane.entry_lanes],
            "exit_lanes": [names.ref(v) for v in lane.exit_lanes],
            "left_boundaries": _segments(lane.left_boundaries, names),
            "right_boundaries": _segments(lane.right_boundaries, names),
            "left_neighbor": _neighbors(lane.left_neighbors, names),
            "right_neighbor": _neighbors(lane.right_neighbors, names),
        })
    for line in rm.road_lines:
        out[line.id] = (names.feature(line.id), {"type": schema.ROAD_LINE_TYPES[line.type],
                                                 "polyline": line.polyline.copy()})
    for edge in rm.road_edges:
        out[edge.id] = (names.feature(edge.id), {"type": schema.ROAD_EDGE_TYPES[edge.type],
                                                 "polyline": edge.polyline.copy()})
    for sign in rm.stop_signs:
        out[sign.id] = (names.feature(sign.id), {
            "type": schema.STOP_SIGN, "lane": [names.ref(v) for v in sign.lanes],
            "position": sign.position.copy()})
    for kind, items in ((schema.CROSSWALK, rm.crosswalks), (schema.SPEED_BUMP, rm.speed_bumps),
                        (schema.DRIVEWAY, rm.driveways)):
        for area in items:
            out[area.id] = (names.feature(area.id), {"type": kind, "polygon": area.polygon.copy()})
    # a source the reader numbered is written in id order (its recorded order), so that
    # reading the file back numbers it the same way
    order = sorted(out) if names.features else list(out)
    return dict(out[fid] for fid in order)


def _dynamic_states(scene: Scene, names: _Names) -> dict[str, dict]:
    sig = scene.signals
    out: dict[str, dict] = {}
    for step, lane, state, point in zip(sig.step.tolist(), sig.lane.tolist(), sig.state.tolist(),
                                        sig.stop_point):
        key = names.feature(lane)
        if key not in out:
            out[key] = {
                "type": schema.TRAFFIC_LIGHT,
                "state": {"object_state": [None] * scene.num_steps},
                "lane": names.ref(lane), "stop_point": None,
                "metadata": {"track_length": scene.num_steps, "type": schema.TRAFFIC_LIGHT,
                             "object_id": key, "dataset": "waymo"},
            }
        out[key]["state"]["object_state"][step] = schema.SIGNAL_STATES[schema.SignalState(state)]
        out[key]["stop_point"] = point.copy()  # ScenarioNet keeps the last stop point
    return out


def scene_to_scenarionet(scene: Scene, *, source_file: str = "", version: str = DEFAULT_VERSION,
                         dataset: str = "waymo") -> dict[str, Any]:
    """The ScenarioNet scenario dict of a scene, with ScenarioNet's summaries.

    A scene read from a source with non-integer ids (``Scene.source_ids``) is written with its
    original track and map-feature ids.
    """
    tr = scene.tracks
    sdc = scene.sdc_track_index
    names = _Names(scene)
    sd: dict[str, Any] = {
        "id": scene.scenario_id,
        "version": version,
        "length": scene.num_steps,
        "tracks": _tracks(scene, names),
        "dynamic_map_states": _dynamic_states(scene, names),
        "map_features": _map_features(scene, names),
    }
    meta: dict[str, Any] = {
        "id": scene.scenario_id, "coordinate": "waymo", "ts": scene.timestamps.copy(),
        "metadrive_processed": False,
        "sdc_id": names.track(int(tr.id[sdc])) if sdc >= 0 else None,
        "dataset": dataset, "scenario_id": scene.scenario_id, "source_file": source_file,
        "track_length": scene.num_steps, "current_time_index": scene.current_time_index,
        "sdc_track_index": sdc,
        "objects_of_interest": [names.track(v) for v in scene.objects_of_interest],
        "tracks_to_predict": {
            names.track(int(tr.id[r.track_index])): {
                "track_index": r.track_index, "track_id": names.track(int(tr.id[r.track_index])),
                "difficulty": int(r.difficulty),
                "object_type": schema.OBJECT_TYPES[ObjectType(int(tr.type[r.track_index]))],
            } for r in scene.tracks_to_predict
        },
    }
    meta["object_summary"] = _object_summary(sd["tracks"])
    meta["number_summary"] = _number_summary(sd, meta["object_summary"])
    sd["metadata"] = meta
    return sd


def _object_summary(tracks: dict[str, dict]) -> dict[str, dict]:
    out = {}
    for key, obj in tracks.items():
        valid = obj["state"]["valid"]
        xy = obj["state"]["position"][valid, :2]
        moved = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()) if len(xy) > 1 else 0.0
        first = np.flatnonzero(valid)
        run = 0
        if first.size:
            rest = valid[first[0]:]
            run = int(np.argmin(rest)) if not rest.all() else int(rest.size)
        out[key] = {"type": obj["type"], "object_id": key, "track_length": int(valid.size),
                    "moving_distance": moved, "valid_length": int(valid.sum()),
                    "continuous_valid_length": run}
    return out


def _number_summary(sd: dict, objects: dict[str, dict]) -> dict[str, Any]:
    each_type: dict[str, int] = collections.Counter(o["type"] for o in objects.values())
    moving = collections.defaultdict(int)
    for o in objects.values():
        if o["moving_distance"] > 1.0:
            moving[o["type"]] += 1
    lights = sd["dynamic_map_states"]
    light_types = {s for lt in lights.values() for s in lt["state"]["object_state"] if s is not None}
    per_step = {str(t): sum(lt["state"]["object_state"][t] is not None for lt in lights.values())
                for t in range(sd["length"])}
    z = [f["polyline"][:, 2] for f in sd["map_features"].values()
         if str(f["type"]).startswith("ROAD_LINE") and len(f["polyline"])]
    return {
        "num_objects": len(objects), "object_types": set(each_type),
        "num_objects_each_type": dict(each_type), "num_moving_objects": sum(moving.values()),
        "num_moving_objects_each_type": moving, "num_traffic_lights": len(lights),
        "num_traffic_light_types": light_types, "num_traffic_light_each_step": per_step,
        "num_map_features": len(sd["map_features"]),
        "map_height_diff": float(np.ptp(np.concatenate(z))) if z else float("-inf"),
    }


def scenarionet_file_name(scene: Scene, version: str = DEFAULT_VERSION, dataset: str = "waymo") -> str:
    return f"sd_{dataset}_{version}_{scene.scenario_id}.pkl"


def write_scenarionet(path: str | PathLike, scene: Scene, **kwargs: Any) -> Path:
    """Write one scenario pickle to ``path``."""
    p = Path(path)
    with open(p, "wb") as fh:
        pickle.dump(scene_to_scenarionet(scene, **kwargs), fh, protocol=PICKLE_PROTOCOL)
    return p


def write_scenarionet_dataset(folder: str | PathLike, scenes: Iterable[Scene],
                              version: str = DEFAULT_VERSION, dataset: str = "waymo") -> list[Path]:
    """Write a ScenarioNet dataset folder: one ``sd_*.pkl`` per scene plus summary and mapping."""
    root = Path(folder)
    root.mkdir(parents=True, exist_ok=True)
    summary: dict[str, dict] = {}
    files = []
    for scene in scenes:
        sd = scene_to_scenarionet(scene, version=version, dataset=dataset)
        name = scenarionet_file_name(scene, version, dataset)
        with open(root / name, "wb") as fh:
            pickle.dump(sd, fh, protocol=PICKLE_PROTOCOL)
        meta = copy.deepcopy(sd["metadata"])
        meta["ts"] = meta["ts"].tolist()
        ns = meta["number_summary"]
        ns["object_types"] = tuple(ns["object_types"])
        ns["num_traffic_light_types"] = tuple(ns["num_traffic_light_types"])
        summary[name] = meta
        files.append(root / name)
    with open(root / SUMMARY_FILE, "wb") as fh:
        pickle.dump(summary, fh, protocol=PICKLE_PROTOCOL)
    with open(root / MAPPING_FILE, "wb") as fh:
        pickle.dump({name: "" for name in summary}, fh, protocol=PICKLE_PROTOCOL)
    return files
