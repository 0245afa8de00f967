"""SUMO's own car-following as a baseline: the ``sumo`` method of evaluation.

SUMO's default car-following (Krauss) drives the converted routes from every route vehicle's
recorded pose and speed at the scene's current step, each with a seeded speed factor; every
other sim agent moves at constant velocity and is an obstacle SUMO's drivers brake for. The
SUMO run is :func:`converters.sumo.baseline.drive_from_current` (its module has the details,
and the converter's quality run beside it); this module gives it the agents' recorded state at
the current step and their constant-velocity future (:mod:`.constant_velocity`), and completes
the steps SUMO did not drive at constant velocity.

One simulation per process (libsumo), so callers run each rollout batch in a fresh worker
process.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from converters.sumo.baseline import drive, prepare_drive
from magail_sumo.scene import Scene

from .constant_velocity import Track, constant_velocity, current_state, fill_constant_velocity


def sumo_rollout(scene: Scene, bundle_dir: Path, seed: int, ids: np.ndarray, n_steps: int
                 ) -> tuple[np.ndarray, ...]:
    """One rollout of SUMO's own car-following (module doc) of the agents ``ids`` (track ids)
    over ``n_steps`` steps after the scene's current step; (x, y, yaw), each (A, n_steps)."""
    return sumo_rollouts(scene, bundle_dir, [seed], ids, n_steps)[0]


def sumo_rollouts(scene: Scene, bundle_dir: Path, seeds: Iterable[int], ids: np.ndarray,
                  n_steps: int) -> list[tuple[np.ndarray, ...]]:
    """:func:`sumo_rollout` of each seed, one SUMO run after another; the bundle, the agents'
    current state and their constant-velocity future are read once for all of them."""
    setup = prepare_drive(scene, bundle_dir, ids, n_steps, current_state(scene, ids),
                          constant_velocity(scene, ids, n_steps))
    return [fill_constant_velocity(scene, ids, Track(*drive(setup, s))) for s in seeds]
