"""SAC's replay: a ring buffer of transitions as CPU tensors, and the batches drawn from the
main and the collision buffers (:mod:`magail_sumo.training.sac`)."""

from __future__ import annotations


import numpy as np
import torch


from ..checkpoints import (tensor_field)

ACT_DIM = 2  #: actions per transition ([accel, steer])

class ReplayBuffer:
    """A ring buffer of transitions as CPU tensors (oldest overwritten first).

    Rows: ``obs`` and ``next_obs`` (obs_dim + 1: the absorbing flag last), ``action``,
    ``reward``, ``done`` (1: no bootstrap).
    """

    FIELDS = ("obs", "action", "reward", "next_obs", "done")

    def __init__(self, capacity: int, width: int, act_dim: int = ACT_DIM) -> None:
        self.capacity, self.width, self.act_dim = int(capacity), int(width), int(act_dim)
        shapes = {"obs": (width,), "action": (act_dim,), "reward": (), "next_obs": (width,),
                  "done": ()}
        self.data = {k: torch.empty((self.capacity, *shapes[k]), dtype=torch.float32)
                     for k in self.FIELDS}
        self.pos = 0
        self.size = 0

    def __len__(self) -> int:
        return self.size

    def add(self, **rows: np.ndarray) -> None:
        """Append N transitions (each field an (N, ...) array)."""
        n = len(rows["reward"])
        if n == 0:
            return
        if n > self.capacity:  # only the newest fit
            rows = {k: v[-self.capacity:] for k, v in rows.items()}
            n = self.capacity
        idx = (self.pos + np.arange(n)) % self.capacity
        t = torch.from_numpy(idx)
        for k in self.FIELDS:
            self.data[k][t] = torch.as_tensor(np.asarray(rows[k], np.float32))
        self.pos = int((self.pos + n) % self.capacity)
        self.size = min(self.size + n, self.capacity)

    def get(self, idx: np.ndarray) -> dict[str, torch.Tensor]:
        t = torch.from_numpy(np.asarray(idx, np.int64))
        return {k: v[t] for k, v in self.data.items()}

    def state_dict(self) -> dict:
        """The stored rows (tensors) and the ring position."""
        return {"pos": self.pos, "size": self.size,
                **{k: v[:self.size].clone() for k, v in self.data.items()}}

    def load_state_dict(self, state: dict) -> None:
        size, pos = state["size"], state["pos"]
        if not (type(size) is int and type(pos) is int and 0 <= size <= self.capacity
                and 0 <= pos < max(self.capacity, 1) and (size == self.capacity or pos == size)):
            raise ValueError("replay buffer size / position do not fit its capacity")
        for k in self.FIELDS:
            v = tensor_field(state[k], f"replay buffer {k}")
            want = (size, *self.data[k].shape[1:])
            if v.dtype != torch.float32 or tuple(v.shape) != want:
                raise ValueError(f"replay buffer {k} is not float32 {want}")
            self.data[k][:size] = v
        self.size, self.pos = size, pos


def collision_count(batch_size: int, share: float, collisions: int) -> int:
    """Transitions of a batch drawn from the collision buffer: ``int(share · batch_size)`` when
    the collision buffer holds at least that many (and it is > 0), else 0."""
    n = int(share * batch_size)
    return n if 0 < n <= collisions else 0


def sample_batch(main: ReplayBuffer, collision: ReplayBuffer, batch_size: int, share: float,
                 rng: np.random.Generator) -> dict[str, torch.Tensor]:
    """A batch of ``batch_size`` transitions (uniform with replacement), the first
    :func:`collision_count` of them from ``collision``, the rest from ``main``."""
    n_col = collision_count(batch_size, share, len(collision))
    parts = []
    if n_col:
        parts.append(collision.get(rng.integers(0, len(collision), n_col)))
    parts.append(main.get(rng.integers(0, len(main), batch_size - n_col)))
    return {k: torch.cat([p[k] for p in parts]) for k in ReplayBuffer.FIELDS}
