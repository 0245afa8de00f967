"""Waymo Open Motion Dataset ``Scenario`` TFRecords: reader and writer (no TensorFlow)."""

from .reader import iter_womd, parse_scenario, scene_from_proto
from .writer import scene_to_proto, write_womd

__all__ = ["iter_womd", "parse_scenario", "scene_from_proto", "scene_to_proto", "write_womd"]
