"""Object tracks of a scene as N×T arrays (N tracks, T time steps)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .base import ArrayDataclass, frozen_array
from .types import ObjectType

#: Per-state float fields, in WOMD ``ObjectState`` order.
STATE_FIELDS: tuple[str, ...] = ("x", "y", "z", "length", "width", "height", "heading", "vx", "vy")


@dataclass(frozen=True, eq=False)
class Tracks(ArrayDataclass):
    """Bounding-box tracks in the scene frame.

    Units: positions and sizes in metres (box centre; ``length`` along the heading),
    ``heading`` in radians counter-clockwise from +x, velocities in m/s (scene frame).
    Values at invalid steps are kept exactly as recorded and carry no meaning.

    :param id: (N,) int64 track ids, unique within the scene.
    :param type: (N,) int8 :class:`ObjectType` values.
    :param x: (N, T) float64 box centre x.
    :param y: (N, T) float64 box centre y.
    :param z: (N, T) float64 box centre z.
    :param length: (N, T) float32 box size along the heading.
    :param width: (N, T) float32 box size across the heading.
    :param height: (N, T) float32 box height.
    :param heading: (N, T) float32 yaw.
    :param vx: (N, T) float32 velocity x.
    :param vy: (N, T) float32 velocity y.
    :param valid: (N, T) bool, whether the state was observed.
    """

    id: np.ndarray
    type: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    length: np.ndarray
    width: np.ndarray
    height: np.ndarray
    heading: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    valid: np.ndarray

    def __post_init__(self) -> None:
        n = np.shape(self.id)[0] if np.ndim(self.id) == 1 else -2
        set_ = object.__setattr__
        try:
            set_(self, "id", frozen_array(self.id, np.int64, (-1,)))
            set_(self, "type", frozen_array(self.type, np.int8, (n,)))
            t = np.shape(self.valid)[1] if np.ndim(self.valid) == 2 else -2
            for name in ("x", "y", "z"):
                set_(self, name, frozen_array(getattr(self, name), np.float64, (n, t)))
            for name in ("length", "width", "height", "heading", "vx", "vy"):
                set_(self, name, frozen_array(getattr(self, name), np.float32, (n, t)))
            set_(self, "valid", frozen_array(self.valid, np.bool_, (n, t)))
        except ValueError as exc:
            raise ValueError(f"Tracks: {exc}") from None

    @property
    def num_tracks(self) -> int:
        return int(self.id.shape[0])

    @property
    def num_steps(self) -> int:
        return int(self.valid.shape[1])

    def count_by_type(self) -> dict[str, int]:
        """Number of tracks of each :class:`ObjectType` (lower-case names, UNSET excluded)."""
        counts = np.bincount(self.type.astype(np.int64), minlength=len(ObjectType))
        return {t.name.lower(): int(counts[t]) for t in ObjectType if t is not ObjectType.UNSET}

    @classmethod
    def empty(cls, num_steps: int) -> "Tracks":
        """Zero tracks over ``num_steps`` steps."""
        z64 = np.zeros((0, num_steps), np.float64)
        z32 = np.zeros((0, num_steps), np.float32)
        return cls(
            id=np.zeros(0, np.int64), type=np.zeros(0, np.int8), x=z64, y=z64, z=z64,
            length=z32, width=z32, height=z32, heading=z32, vx=z32, vy=z32,
            valid=np.zeros((0, num_steps), bool),
        )
