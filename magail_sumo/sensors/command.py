"""High-level route command of each agent: turn left / go straight / turn right at its next
junction (the optional ``command`` observation feature, :class:`ObservationConfig` ``command``).

The route of a vehicle is its recorded path (the track it replays as expert, the path its SUMO
route was matched to), from its first to its last valid state. The agent's progress point on it
is the recorded state nearest to the agent's current position (m, scene frame); the command is
the turn of the route between that point and the point ``lookahead`` m further along the route
(or the route's end when it is nearer): the wrapped heading change ``Δ`` (rad, CCW positive)
of the recorded headings gives ``left`` when ``Δ > TURN``, ``right`` when ``Δ < −TURN``,
``straight`` otherwise. With the default 30 m lookahead this is the manoeuvre through the next
junction a vehicle approaches or is in (WOMD maps carry no reliable junction flag, so the
junction is where the route turns). Vectorised over all agents of a step ((A, T) arrays).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: command indices (columns of the one-hot, ``command_left`` / ``_straight`` / ``_right``)
LEFT, STRAIGHT, RIGHT = 0, 1, 2
COMMANDS = ("left", "straight", "right")
#: feature names of the one-hot in the observation (``ObservationConfig.command``)
COMMAND_NAMES = [f"command_{c}" for c in COMMANDS]
#: heading change (rad) above which the route turns (30°)
TURN = np.pi / 6


def command_index(delta: np.ndarray) -> np.ndarray:
    """(A,) command index of route heading changes ``delta`` (rad, wrapped to [-pi, pi))."""
    d = np.asarray(delta, np.float64)
    return np.where(d > TURN, LEFT, np.where(d < -TURN, RIGHT, STRAIGHT)).astype(np.int64)


def one_hot(index: np.ndarray) -> np.ndarray:
    """(A, 3) float32 one-hot of command indices."""
    out = np.zeros((np.asarray(index).shape[0], len(COMMANDS)), np.float32)
    out[np.arange(out.shape[0]), index] = 1.0
    return out


@dataclass(frozen=True)
class RouteCommands:
    """Per-track recorded routes of a scene, for :meth:`commands` (built once per scene).

    :param x, y: (N, T) recorded positions (m, scene frame; NaN where the track is invalid).
    :param heading: (N, T) recorded headings (rad).
    :param arc: (N, T) distance along the route from its first valid state (m; NaN invalid).
    :param lookahead: route distance ahead at which the turn is read (m).
    """

    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    arc: np.ndarray
    lookahead: float

    @classmethod
    def build(cls, tracks, lookahead: float = 30.0) -> "RouteCommands":
        valid = np.asarray(tracks.valid, bool)
        x = np.where(valid, tracks.x, np.nan).astype(np.float64)
        y = np.where(valid, tracks.y, np.nan).astype(np.float64)
        # step lengths between consecutive valid states (a gap counts as the straight line)
        xf = _fill_forward(x, valid)
        yf = _fill_forward(y, valid)
        seg = np.hypot(np.diff(xf, axis=1), np.diff(yf, axis=1))
        arc = np.concatenate([np.zeros((x.shape[0], 1)), np.nancumsum(seg, axis=1)], axis=1)
        arc = np.where(valid, arc, np.nan)
        return cls(x, y, np.asarray(tracks.heading, np.float64), arc, float(lookahead))

    def commands(self, rows: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(A, 3) float32 one-hot commands of agents on track ``rows`` at positions (x, y)."""
        rows = np.asarray(rows, np.int64)
        if rows.size == 0:
            return np.zeros((0, len(COMMANDS)), np.float32)
        d = np.hypot(self.x[rows] - np.asarray(x, np.float64)[:, None],
                     self.y[rows] - np.asarray(y, np.float64)[:, None])
        at = np.argmin(np.where(np.isnan(d), np.inf, d), axis=1)
        arc = self.arc[rows]
        a = np.arange(rows.size)
        goal = arc[a, at] + self.lookahead
        # last valid state within the lookahead (the first past it when there is one)
        ahead = np.where(np.isnan(arc), -np.inf, arc)
        past = ahead >= goal[:, None]
        last_valid = arc.shape[1] - 1 - np.argmax(~np.isnan(arc[:, ::-1]), axis=1)
        to = np.where(past.any(axis=1), np.argmax(past, axis=1), last_valid)
        h = self.heading[rows]
        delta = (h[a, to] - h[a, at] + np.pi) % (2 * np.pi) - np.pi
        return one_hot(command_index(delta))


def _fill_forward(v: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``v`` with each invalid entry replaced by the last valid one before it (the first valid
    one before any)."""
    n, t = v.shape
    idx = np.where(valid, np.arange(t)[None, :], 0)
    idx = np.maximum.accumulate(idx, axis=1)
    first = np.argmax(valid, axis=1)
    idx = np.where(valid.cumsum(axis=1) == 0, first[:, None], idx)
    return v[np.arange(n)[:, None], idx]
