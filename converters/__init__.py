"""Readers and writers of recorded-scene formats (WOMD, ScenarioNet), and (later) SUMO builders."""

from .scene_files import (SceneRecord, detect_format, find_scene, iter_scene_records, iter_scenes,
                          load_scene)

__all__ = ["SceneRecord", "detect_format", "find_scene", "iter_scene_records", "iter_scenes",
           "load_scene"]
