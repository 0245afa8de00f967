"""GPUDrive / Nocturne / PufferDrive JSON scenes (WOMD converted to JSON): reader and writer."""

from .reader import iter_gpudrive, load_gpudrive, scene_from_gpudrive
from .writer import scene_to_gpudrive, write_gpudrive

__all__ = ["iter_gpudrive", "load_gpudrive", "scene_from_gpudrive", "scene_to_gpudrive",
           "write_gpudrive"]
