"""Sensor emulation over all vehicles of a step at once (lidar, side and lane-line detectors, ...)."""

from .raycast import SegmentGrid, box_edges, cast, polyline_segments

__all__ = ["SegmentGrid", "box_edges", "cast", "polyline_segments"]
