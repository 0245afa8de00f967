"""The policy-driven vehicles of an episode as one typed state, shared by both envs.

A :class:`Fleet` holds one row ``k`` per vehicle the env may hand to a policy in the episode
(recorded scenes: the controlled tracks, fixed at reset; cities: each vehicle chosen as an
agent, appended as it joins). Rows never move, so ``k`` is the vehicle's index for the whole
episode. Per row:

* bicycle state ``x, y`` (box centre, m), ``yaw`` (rad, CCW from +x), ``speed`` (m/s along the
  heading), scene frame (:mod:`magail_sumo.sim.dynamics`), the agent's pose;
* box ``length, width`` (m); destination ``dest`` (x, y m) and ``dest_yaw`` (rad);
* ``prev_action``: the last clean normalised action (the ego sensor's previous action);
* flags ``active`` (a live agent now), ``joined`` (was an agent this episode: a row that
  joined and is no longer active has left for good), ``in_sumo`` (a vehicle of that name is in
  the SUMO simulation, so the env places it there each step);
* running counts ``nan_actions`` / ``clipped_actions`` of non-finite / out-of-range actions;
* ``path``: the row of the vehicle's reference path in the env's
  :class:`~magail_sumo.sim.paths.Paths` (-1: none) and ``hint``: its progress point's index on
  it (route-relative control and the route look-ahead, :mod:`magail_sumo.sim.tracking`);
* ``speed_factor``: the driver's desired speed over the road's (1 unless the env knows it:
  a city reads SUMO's, :mod:`magail_sumo.sensors.units.speed_factor`).

Arrays may have spare rows beyond ``len(fleet)`` (zero, every flag False): a city fleet grows
by doubling (:meth:`Fleet.add`) instead of reallocating per joiner. Methods are small and work
on index arrays ``k`` (no per-vehicle Python loops, except for the per-name PettingZoo dicts).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from magail_sumo.sim import dynamics, tracking
from magail_sumo.sim.paths import Paths


#: what a grown row holds where it is not 0
GROW_FILL = {"path": -1, "speed_factor": 1.0}


@dataclass(frozen=True)
class AgentStates:
    """Bicycle state of the live agents, in ``env.agents`` order.

    :param rows: (A,) track rows in ``scene.tracks`` (city env: fleet rows).
    :param state: their state (scene frame). :param wheelbase: (A,) m.
    """

    names: list[str]
    rows: np.ndarray
    state: dynamics.VehicleState
    wheelbase: np.ndarray


@dataclass(eq=False)
class Fleet:
    """Per-vehicle arrays of an episode's (possible) agents (module doc); rows ``0..len-1``."""

    names: list[str]
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    length: np.ndarray
    width: np.ndarray
    dest: np.ndarray
    dest_yaw: np.ndarray
    prev_action: np.ndarray
    active: np.ndarray
    joined: np.ndarray
    in_sumo: np.ndarray
    nan_actions: np.ndarray
    clipped_actions: np.ndarray
    path: np.ndarray
    hint: np.ndarray
    speed_factor: np.ndarray
    #: name -> row
    index: dict[str, int] = field(default_factory=dict)

    # ------------------------------------------------------------------ building
    @classmethod
    def empty(cls, capacity: int) -> "Fleet":
        """A fleet of no vehicles with room for ``capacity`` before it grows."""
        z = lambda dtype=np.float64: np.zeros(capacity, dtype)  # noqa: E731
        return cls([], z(), z(), z(), z(), z(), z(), np.zeros((capacity, 2)), z(),
                   np.zeros((capacity, dynamics.ACTION_SIZE)), z(bool), z(bool), z(bool),
                   z(np.int64), z(np.int64), np.full(capacity, -1, np.int64), z(np.int64),
                   np.ones(capacity))

    @classmethod
    def roster(cls, names: list[str], length: np.ndarray, width: np.ndarray, dest: np.ndarray,
               dest_yaw: np.ndarray) -> "Fleet":
        """A fleet of the given vehicles (none joined yet; boxes and destinations copied with
        their dtypes)."""
        f = cls.empty(len(names))
        f.names = list(names)
        f.index = {a: k for k, a in enumerate(f.names)}
        f.length, f.width = np.array(length), np.array(width)
        f.dest, f.dest_yaw = np.array(dest), np.array(dest_yaw)
        return f

    def __len__(self) -> int:
        return len(self.names)

    @property
    def capacity(self) -> int:
        """Rows the arrays have room for."""
        return self.x.shape[0]

    def grow(self, n: int) -> None:
        """Make room for at least ``n`` rows (doubling; new rows zero)."""
        size = self.capacity
        if n <= size:
            return
        new = max(n, 2 * size)
        for f in fields(self):
            old = getattr(self, f.name)
            if isinstance(old, np.ndarray):
                setattr(self, f.name, resized(old, new, GROW_FILL.get(f.name, 0)))

    def add(self, name: str, x: float, y: float, yaw: float, speed: float, length: float,
            width: float) -> int:
        """Append a vehicle with its state and box (not yet joined); its row."""
        k = len(self.names)
        self.grow(k + 1)
        self.names.append(name)
        self.index[name] = k
        self.x[k], self.y[k], self.yaw[k] = x, y, yaw
        self.speed[k], self.length[k], self.width[k] = speed, length, width
        return k

    # ------------------------------------------------------------------ queries
    def live(self) -> np.ndarray:
        """(A,) sorted rows of the active agents."""
        return np.flatnonzero(self.active)

    def names_of(self, k: np.ndarray) -> list[str]:
        return [self.names[i] for i in k]

    def rows_of(self, names) -> np.ndarray:
        """(A,) rows of agent ``names``."""
        return np.array([self.index[a] for a in names], np.int64)

    def state(self, k: np.ndarray) -> dynamics.VehicleState:
        """Bicycle state of rows ``k`` (copies)."""
        return dynamics.VehicleState(self.x[k], self.y[k], self.yaw[k], self.speed[k])

    def position(self, k: np.ndarray) -> np.ndarray:
        """(A, 2) box centres of rows ``k`` (m)."""
        return np.stack([self.x[k], self.y[k]], axis=1)

    def wheelbase(self, k: np.ndarray) -> np.ndarray:
        """(A,) wheelbase of rows ``k`` (m; :data:`~magail_sumo.sim.dynamics.WHEELBASE_RATIO`
        of the box length)."""
        return dynamics.WHEELBASE_RATIO * self.length[k]

    def left(self) -> np.ndarray:
        """(N,) bool: rows that joined and are no longer active (gone for the episode)."""
        return self.joined & ~self.active

    # ------------------------------------------------------------------ updates
    def set_state(self, k: np.ndarray, st: dynamics.VehicleState) -> None:
        self.x[k], self.y[k], self.yaw[k], self.speed[k] = st.x, st.y, st.yaw, st.speed

    def join(self, k: np.ndarray, st: dynamics.VehicleState | None = None) -> None:
        """Rows ``k`` become live agents (at state ``st`` when given)."""
        if st is not None:
            self.set_state(k, st)
        self.joined[k] = self.active[k] = True

    def drive(self, k: np.ndarray, action: np.ndarray, limits: dynamics.BicycleLimits,
              layout: str, dt: float, paths: Paths | None = None) -> None:
        """Move rows ``k`` one step of ``dt`` s by the bicycle model under clean normalised
        (A, 2) ``action`` (in ``layout``, clipped to ``limits``); it becomes their previous
        action (with a steering rate limit, ``limits.max_steer_rate``, the steering applied).
        The ``accel_offset`` layout steers along the rows' reference paths in
        ``paths`` (:func:`magail_sumo.sim.tracking.follow`); a row without one keeps its
        heading."""
        accel, second = dynamics.denormalise(action, limits, layout)
        state, wheelbase = self.state(k), self.wheelbase(k)
        if layout == "accel_offset":
            accel = tracking.no_reverse(accel, state.speed, dt)
            steer = np.zeros(k.size)
            on = self.path[k] >= 0
            if on.any() and paths is not None:
                sub = dynamics.VehicleState(state.x[on], state.y[on], state.yaw[on],
                                            state.speed[on])
                steer[on], self.hint[k[on]] = tracking.follow(
                    paths, self.path[k[on]], self.hint[k[on]], sub, wheelbase[on], second[on],
                    limits)
        else:
            steer = second
            if limits.max_steer_rate > 0:  # the applied steering becomes the previous action
                _, prev = dynamics.denormalise(self.prev_action[k], limits, layout)
                steer = dynamics.limit_steer_rate(steer, prev, limits, dt)
                action = dynamics.normalise(accel, steer, limits, layout)
        self.set_state(k, dynamics.step(state, accel, steer, wheelbase, dt, limits))
        self.prev_action[k] = action

    def count_fixes(self, k: np.ndarray, nonfinite: np.ndarray, outside: np.ndarray) -> None:
        """Add one step's non-finite / clipped action masks of rows ``k`` to their counts."""
        self.nan_actions[k] += nonfinite
        self.clipped_actions[k] += outside

    def agent_states(self, k: np.ndarray, rows: np.ndarray) -> AgentStates:
        """:class:`AgentStates` of rows ``k`` (``rows``: what the env reports as their rows)."""
        return AgentStates(self.names_of(k), rows, self.state(k), self.wheelbase(k))


def resized(arr: np.ndarray, n: int, fill=0) -> np.ndarray:
    """``arr`` with ``n`` rows: its rows first, then rows of ``fill`` (same dtype; a copy)."""
    out = np.full((n,) + arr.shape[1:], fill, arr.dtype)
    m = min(n, arr.shape[0])
    out[:m] = arr[:m]
    return out
