"""ScenarioNet / MetaDrive scenario pickles: restricted reader and writer."""

from .reader import dataset_files, iter_scenarionet, load_scenarionet, scene_from_scenarionet
from .safe_pickle import UnsafePickleError, safe_load, safe_loads
from .writer import (
    scene_to_scenarionet, scenarionet_file_name, write_scenarionet, write_scenarionet_dataset,
)

__all__ = [
    "UnsafePickleError", "dataset_files", "iter_scenarionet", "load_scenarionet", "safe_load",
    "safe_loads", "scene_from_scenarionet", "scene_to_scenarionet", "scenarionet_file_name",
    "write_scenarionet", "write_scenarionet_dataset",
]
