"""Recorded traffic-signal states, one row per (time step, controlled lane) record."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .base import ArrayDataclass, frozen_array
from .types import SignalState


@dataclass(frozen=True, eq=False)
class SignalStates(ArrayDataclass):
    """Per-step traffic-signal lane states as a flat table of K records.

    Records are ordered by ``step``, and within a step in recorded order.

    :param step: (K,) int32 time-step index of the record.
    :param lane: (K,) int64 id of the controlled lane.
    :param state: (K,) int8 :class:`SignalState`.
    :param stop_point: (K, 3) float64 stopping point (metres, scene frame).
    """

    step: np.ndarray
    lane: np.ndarray
    state: np.ndarray
    stop_point: np.ndarray

    def __post_init__(self) -> None:
        k = int(np.shape(self.step)[0]) if np.ndim(self.step) == 1 else -2
        try:
            object.__setattr__(self, "step", frozen_array(self.step, np.int32, (-1,)))
            object.__setattr__(self, "lane", frozen_array(self.lane, np.int64, (k,)))
            object.__setattr__(self, "state", frozen_array(self.state, np.int8, (k,)))
            object.__setattr__(
                self, "stop_point",
                frozen_array(np.reshape(self.stop_point, (-1, 3)), np.float64, (k, 3)),
            )
        except ValueError as exc:
            raise ValueError(f"SignalStates: {exc}") from None
        if k > 1 and np.any(np.diff(self.step) < 0):
            raise ValueError("SignalStates: records must be ordered by step")

    def __len__(self) -> int:
        return int(self.step.shape[0])

    @classmethod
    def empty(cls) -> "SignalStates":
        return cls(np.zeros(0, np.int32), np.zeros(0, np.int64), np.zeros(0, np.int8),
                   np.zeros((0, 3)))

    def at_step(self, step: int) -> "SignalStates":
        """The records of one time step."""
        lo, hi = np.searchsorted(self.step, [step, step + 1])
        return SignalStates(self.step[lo:hi], self.lane[lo:hi], self.state[lo:hi],
                            self.stop_point[lo:hi])

    @property
    def lanes(self) -> np.ndarray:
        """Sorted unique ids of the lanes that have signal records."""
        return np.unique(self.lane)

    def known(self) -> np.ndarray:
        """(K,) bool mask of records whose state is not UNKNOWN."""
        return self.state != SignalState.UNKNOWN
