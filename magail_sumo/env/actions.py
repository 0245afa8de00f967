"""Agent action dicts (PettingZoo) to clean arrays, counting what had to be fixed."""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np


def action_array(actions: Mapping[str, Any], names: Sequence[str]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, 2) normalised actions of agents ``names`` in [-1, 1], plus (A,) masks of the entries
    that were non-finite or missing (replaced by 0) and of those outside [-1, 1] (clipped).

    Nothing non-finite or out of range ever reaches the vehicle model or SUMO.
    """
    raw = np.full((len(names), 2), np.nan)
    for i, name in enumerate(names):  # dict → array: the PettingZoo interface is per agent
        v = actions.get(name)
        if v is not None:
            raw[i] = np.asarray(v, np.float64).reshape(2)
    nonfinite = ~np.isfinite(raw).all(axis=1)
    clean = np.nan_to_num(raw, nan=0.0, posinf=0.0, neginf=0.0)
    outside = (np.abs(clean) > 1.0).any(axis=1)
    return np.clip(clean, -1.0, 1.0), nonfinite, outside
