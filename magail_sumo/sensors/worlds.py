"""Several independent worlds in one set of boxes: which road users each agent can meet.

A batched env (:class:`~magail_sumo.env.batched.BatchedSceneEnv`) steps ``W`` copies
("worlds": the rollouts of one scene) of a recorded scene as one fleet. Its step's
:class:`~magail_sumo.sensors.base.Boxes` hold every world's agents plus the log-replayed road
users, which are the same in every world and so are stored once ("shared"). An agent must only
see, hit and follow the road users of its own world and the shared ones: the sensors that read
other road users (lidar, leader), the gap guard and the collision test read
:class:`BoxGroups` for that.

Buckets: box rows of world ``w`` are ``rows[offsets[w]:offsets[w + 1]]``, the shared rows
``rows[offsets[W]:offsets[W + 1]]``; rows ascend within a bucket. An agent's candidates are its
world's bucket then the shared one; with the batched env's layout (every world's agents first,
world-major, then the shared road users) that is the order of the boxes a single-world env
builds, so first-found and lowest-row choices are the same as there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: ``BoxGroups.world`` of a box every world sees
SHARED = -1


@dataclass(frozen=True)
class BoxGroups:
    """Boxes of ``W`` worlds (module doc).

    :param world: (N,) int64 world of each box (:data:`SHARED`: every world's).
    :param offsets: (W + 2,) int64 bucket bounds into :attr:`rows` (bucket ``W``: shared).
    :param rows: (N,) int64 box rows by bucket, ascending within each.
    """

    world: np.ndarray
    offsets: np.ndarray
    rows: np.ndarray

    @classmethod
    def of(cls, world: np.ndarray, n_worlds: int) -> "BoxGroups":
        """The groups of boxes whose worlds are ``world`` (values in ``[0, n_worlds)`` or
        :data:`SHARED`)."""
        world = np.asarray(world, np.int64)
        if world.size and (world.max() >= n_worlds or world.min() < SHARED):
            raise ValueError(f"box worlds must be in [0, {n_worlds}) or {SHARED}")
        bucket = np.where(world == SHARED, n_worlds, world)
        offsets = np.zeros(n_worlds + 2, np.int64)
        np.add.at(offsets, bucket + 1, 1)
        return cls(world, np.cumsum(offsets), np.argsort(bucket, kind="stable").astype(np.int64))

    @classmethod
    def single(cls, n: int) -> "BoxGroups":
        """``n`` boxes of one world (none shared)."""
        return cls(np.zeros(n, np.int64), np.array([0, n, n], np.int64),
                   np.arange(n, dtype=np.int64))

    @property
    def n_worlds(self) -> int:
        return int(self.offsets.size - 2)

    def candidates(self, index: np.ndarray) -> np.ndarray:
        """(A, M) box rows agents at box rows ``index`` may meet: their world's boxes (their
        own included) then the shared ones, ascending within each, padded with -1."""
        index = np.asarray(index, np.int64)
        w = self.world[index]
        if (w == SHARED).any():
            raise ValueError("an observing agent must belong to a world")
        n_shared = int(self.offsets[-1] - self.offsets[-2])
        own = self.offsets[w + 1] - self.offsets[w]
        m = int(own.max(initial=0)) + n_shared
        j = np.arange(m)[None, :]
        in_own = j < own[:, None]
        pos = np.where(in_own, self.offsets[w][:, None] + j,
                       self.offsets[-2] + j - own[:, None])
        ok = in_own | (j < (own + n_shared)[:, None])
        return np.where(ok, self.rows[np.minimum(pos, max(self.rows.size - 1, 0))], -1)
