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

    def act_batch(self, observations: np.ndarray, worlds: np.ndarray,
                  agents: np.ndarray | None = None) -> np.ndarray:
        """(n, 2) actions of every world's agents (grouped by ``worlds``, ascending, each
        world's in sorted-name order), world ``w`` drawing from its own stream
        (:meth:`reseed_worlds`) as :meth:`act` does (``agents``, their keys, unused)."""
        counts = np.bincount(np.asarray(worlds, np.int64), minlength=len(self.world_rngs))
        parts = [rng.uniform(-1.0, 1.0, (int(c), ACTION_SIZE)).astype(np.float32)
                 for c, rng in zip(counts, self.world_rngs, strict=True)]
        return np.concatenate(parts) if parts else np.zeros((0, ACTION_SIZE), np.float32)

    def act(self, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        names = sorted(observations)
        a = self.rng.uniform(-1.0, 1.0, (len(names), ACTION_SIZE)).astype(np.float32)
        return dict(zip(names, a))
