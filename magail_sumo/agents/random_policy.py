"""Uniform random actions: the ``random`` policy."""

from __future__ import annotations

import numpy as np

from magail_sumo.sim.dynamics import ACTION_SIZE


class RandomPolicy:
    """Uniform random actions in [-1, 1]², seeded (agents served in sorted-name order)."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def reseed(self, seed: int) -> None:
        """Draw from here on as ``RandomPolicy(seed)`` does."""
        self.rng = np.random.default_rng(seed)

    def act(self, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        names = sorted(observations)
        a = self.rng.uniform(-1.0, 1.0, (len(names), ACTION_SIZE)).astype(np.float32)
        return dict(zip(names, a))
