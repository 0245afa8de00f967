"""Sensor emulation over all vehicles of a step at once (lidar, side and lane-line detectors, ...).

Sensors are units (:mod:`.base`: names, bounds and a reading over a road map and a light
source; one module each in :mod:`.units`); :class:`.observation.SensorSuite` concatenates them.
"""

from . import units  # noqa: F401 - registers the built-in sensors (units import .base)
from .raycast import SegmentGrid, box_edges, cast, polyline_segments

__all__ = ["SegmentGrid", "box_edges", "cast", "polyline_segments"]
