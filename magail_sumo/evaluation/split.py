"""Train / test splits of scene files (``configs/splits/*.yaml``): the generalisation protocol.

The split reader lives in :mod:`magail_sumo.splits` (low in the package, so that a training
config can take its scenes from a split without importing evaluation); this module re-exports
it for the evaluation code and the benchmarks.
"""

from __future__ import annotations

from magail_sumo.splits import PARTS, SceneSplit, load_split, scene_stem

__all__ = ["PARTS", "SceneSplit", "load_split", "scene_stem"]
