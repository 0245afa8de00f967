"""Recorded scenes in and out: readers and writers of the scene formats (:mod:`.womd`,
:mod:`.scenarionet`; :func:`find_scene` / :func:`iter_scenes` detect the format), and the
scene-to-SUMO scenario builder with its bundle layout (:mod:`.sumo`)."""

from .scene_files import (SceneRecord, detect_format, find_scene, iter_scene_records, iter_scenes,
                          load_scene)

__all__ = ["SceneRecord", "detect_format", "find_scene", "iter_scene_records", "iter_scenes",
           "load_scene"]
