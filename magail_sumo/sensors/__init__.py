"""Sensor emulation over all vehicles of a step at once (lidar, side and lane-line detectors, ...)."""

from .raycast import box_edges, candidate_pairs, cast, point_segment_distance

__all__ = ["box_edges", "candidate_pairs", "cast", "point_segment_distance"]
