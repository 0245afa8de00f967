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

    def reseed_worlds(self, seeds) -> None:
        """Batched rollouts: world ``w`` draws as ``RandomPolicy(seeds[w])`` does."""
        self.world_rngs = [np.random.default_rng(s) for s in seeds]

    def act_worlds(self, observations: list[dict[str, np.ndarray]]
                   ) -> list[dict[str, np.ndarray]]:
        """Each world's :meth:`act`, from its own stream (:meth:`reseed_worlds`)."""
        out = []
        for d, rng in zip(observations, self.world_rngs, strict=True):
            names = sorted(d)
            a = rng.uniform(-1.0, 1.0, (len(names), ACTION_SIZE)).astype(np.float32)
            out.append(dict(zip(names, a)))
        return out

    def act(self, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        names = sorted(observations)
        a = self.rng.uniform(-1.0, 1.0, (len(names), ACTION_SIZE)).astype(np.float32)
        return dict(zip(names, a))
