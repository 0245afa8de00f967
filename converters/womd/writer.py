"""Write :class:`~magail_sumo.scene.Scene` objects as WOMD ``Scenario`` TFRecord files."""

from __future__ import annotations

from os import PathLike
from typing import Iterable

import numpy as np

from converters.tfrecord import write_records
from converters.womd.protos import scenario_pb2 as pb
from magail_sumo.scene import BoundarySegment, LaneNeighbor, RoadMap, Scene


def scene_to_proto(scene: Scene) -> pb.Scenario:
    """Build the ``Scenario`` message of a scene (one DynamicMapState per time step)."""
    msg = pb.Scenario(scenario_id=scene.scenario_id, current_time_index=scene.current_time_index)
    msg.timestamps_seconds.extend(scene.timestamps.tolist())
    if scene.sdc_track_index >= 0:
        msg.sdc_track_index = scene.sdc_track_index
    msg.objects_of_interest.extend(scene.objects_of_interest)
    for req in scene.tracks_to_predict:
        msg.tracks_to_predict.add(track_index=req.track_index, difficulty=int(req.difficulty))
    _add_tracks(msg, scene)
    _add_map(msg, scene.roadmap)
    _add_signals(msg, scene)
    return msg


def _add_tracks(msg: pb.Scenario, scene: Scene) -> None:
    tr = scene.tracks
    columns = [getattr(tr, k).tolist() for k in
               ("x", "y", "z", "length", "width", "height", "heading", "vx", "vy", "valid")]
    for i in range(tr.num_tracks):
        track = msg.tracks.add(id=int(tr.id[i]), object_type=int(tr.type[i]))
        rows = zip(*(c[i] for c in columns))
        track.states.extend(
            pb.ObjectState(center_x=x, center_y=y, center_z=z, length=ln, width=w, height=h,
                           heading=hd, velocity_x=vx, velocity_y=vy, valid=v)
            for x, y, z, ln, w, h, hd, vx, vy, v in rows
        )


def _set_points(field, points: np.ndarray) -> None:
    field.extend(pb.MapPoint(x=x, y=y, z=z) for x, y, z in points.tolist())


def _set_segments(field, segs: Iterable[BoundarySegment]) -> None:
    for s in segs:
        field.add(lane_start_index=s.lane_start_index, lane_end_index=s.lane_end_index,
                  boundary_feature_id=s.boundary_feature_id, boundary_type=int(s.boundary_type))


def _set_neighbors(field, nbs: Iterable[LaneNeighbor]) -> None:
    for n in nbs:
        out = field.add(feature_id=n.feature_id, self_start_index=n.self_start_index,
                        self_end_index=n.self_end_index, neighbor_start_index=n.neighbor_start_index,
                        neighbor_end_index=n.neighbor_end_index)
        _set_segments(out.boundaries, n.boundaries)


def _add_map(msg: pb.Scenario, rm: RoadMap) -> None:
    for lane in rm.lanes:
        f = msg.map_features.add(id=lane.id)
        ln = f.lane
        ln.speed_limit_mph = lane.speed_limit_mph
        ln.type = int(lane.type)
        ln.interpolating = lane.interpolating
        _set_points(ln.polyline, lane.polyline)
        ln.entry_lanes.extend(lane.entry_lanes)
        ln.exit_lanes.extend(lane.exit_lanes)
        _set_neighbors(ln.left_neighbors, lane.left_neighbors)
        _set_neighbors(ln.right_neighbors, lane.right_neighbors)
        _set_segments(ln.left_boundaries, lane.left_boundaries)
        _set_segments(ln.right_boundaries, lane.right_boundaries)
    for line in rm.road_lines:
        f = msg.map_features.add(id=line.id)
        f.road_line.type = int(line.type)
        _set_points(f.road_line.polyline, line.polyline)
    for edge in rm.road_edges:
        f = msg.map_features.add(id=edge.id)
        f.road_edge.type = int(edge.type)
        _set_points(f.road_edge.polyline, edge.polyline)
    for sign in rm.stop_signs:
        f = msg.map_features.add(id=sign.id)
        f.stop_sign.lane.extend(sign.lanes)
        x, y, z = sign.position.tolist()
        f.stop_sign.position.CopyFrom(pb.MapPoint(x=x, y=y, z=z))
    for kind, items in (("crosswalk", rm.crosswalks), ("speed_bump", rm.speed_bumps),
                        ("driveway", rm.driveways)):
        for area in items:
            f = msg.map_features.add(id=area.id)
            _set_points(getattr(f, kind).polygon, area.polygon)


def _add_signals(msg: pb.Scenario, scene: Scene) -> None:
    sig = scene.signals
    per_step = [msg.dynamic_map_states.add() for _ in range(scene.num_steps)]
    for step, lane, state, (x, y, z) in zip(sig.step.tolist(), sig.lane.tolist(),
                                            sig.state.tolist(), sig.stop_point.tolist()):
        ls = per_step[step].lane_states.add(lane=lane, state=state)
        ls.stop_point.CopyFrom(pb.MapPoint(x=x, y=y, z=z))


def write_womd(path: str | PathLike, scenes: Iterable[Scene], compress: bool | None = None) -> int:
    """Write scenes as a (multi-record) TFRecord shard; gzip when the name ends in .gz.

    :returns: number of scenes written.
    """
    return write_records(path, (scene_to_proto(s).SerializeToString() for s in scenes), compress)
