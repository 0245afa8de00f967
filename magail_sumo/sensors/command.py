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

The route look-ahead (the optional ``route`` observation feature, ``ObservationConfig.
route_points``) reads the same routes: :meth:`RouteCommands.ahead` gives the route's position
``d`` m along it past the progress point (linear between recorded states; the route's last
valid state when the route ends sooner), in the agent's ego frame; :meth:`RouteCommands.
stop_ahead` how far along it the route ends with its driver standing (the ``route_stop``
feature).
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
#: a recorded speed (m/s) below which a driver stands still (WOMD's standing cars read up to
#: a few tenths from position noise)
STANDING = 0.5


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
    :param fx, fy, farc: x, y and arc with each invalid entry replaced by the last valid one
        before it (the first valid one before any): non-decreasing ``farc``, for
        :meth:`ahead`.
    :param end_arc: (N,) arc (m) of each track's last valid state where its recorded speed
        there is below :data:`STANDING` (the route ends standing), NaN otherwise (no valid
        state, the driver moving at its end, or tracks given without velocities ``vx``,
        ``vy``), for :meth:`stop_ahead`.
    """

    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    arc: np.ndarray
    lookahead: float
    fx: np.ndarray
    fy: np.ndarray
    farc: np.ndarray
    end_arc: np.ndarray | None = None

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
        farc = arc.copy()
        arc = np.where(valid, arc, np.nan)
        end_arc = np.full(valid.shape[0], np.nan)
        if getattr(tracks, "vx", None) is not None:  # recorded velocities: standing ends
            last = valid.shape[1] - 1 - np.argmax(valid[:, ::-1], axis=1)
            n = np.arange(valid.shape[0])
            speed = np.hypot(np.asarray(tracks.vx, np.float64)[n, last],
                             np.asarray(tracks.vy, np.float64)[n, last])
            end_arc = np.where(valid.any(axis=1) & (speed < STANDING), farc[n, last], np.nan)
        return cls(x, y, np.asarray(tracks.heading, np.float64), arc, float(lookahead),
                   xf, yf, farc, end_arc)

    def _progress(self, rows: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(A,) index of the recorded state of track ``rows`` nearest to (x, y)."""
        d = np.hypot(self.x[rows] - np.asarray(x, np.float64)[:, None],
                     self.y[rows] - np.asarray(y, np.float64)[:, None])
        return np.argmin(np.where(np.isnan(d), np.inf, d), axis=1)

    def ahead(self, rows: np.ndarray, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
              distances) -> np.ndarray:
        """(A, 2·P) float32 route look-ahead of agents on track ``rows`` at poses (x, y, yaw)
        (m, rad; scene frame): for each of the P ``distances`` (m), the ego-frame x, y (m) of
        the recorded route ``distance`` m past the agent's progress point (its recorded state
        nearest to (x, y)); the route's last valid state where the route ends sooner."""
        rows = np.asarray(rows, np.int64)
        dist = np.asarray(distances, np.float64)
        if rows.size == 0:
            return np.zeros((0, 2 * dist.size), np.float32)
        a = np.arange(rows.size)
        at = self._progress(rows, x, y)
        farc, fx, fy = self.farc[rows], self.fx[rows], self.fy[rows]
        target = farc[a, at][:, None] + dist[None, :]  # (A, P)
        t = farc.shape[1]
        j = (farc[:, None, :] <= target[:, :, None]).sum(axis=2) - 1  # last state not past it
        j = np.clip(j, 0, t - 1)
        k = np.minimum(j + 1, t - 1)
        ai = a[:, None]
        span = farc[ai, k] - farc[ai, j]
        frac = np.where(span > 0, (target - farc[ai, j]) / np.where(span > 0, span, 1.0), 0.0)
        frac = np.clip(frac, 0.0, 1.0)  # past the route's end: its last state
        px = fx[ai, j] + frac * (fx[ai, k] - fx[ai, j])
        py = fy[ai, j] + frac * (fy[ai, k] - fy[ai, j])
        dx = px - np.asarray(x, np.float64)[:, None]
        dy = py - np.asarray(y, np.float64)[:, None]
        c = np.cos(np.asarray(yaw, np.float64))[:, None]
        sn = np.sin(np.asarray(yaw, np.float64))[:, None]
        out = np.empty((rows.size, dist.size, 2), np.float32)
        out[:, :, 0] = c * dx + sn * dy
        out[:, :, 1] = -sn * dx + c * dy
        return out.reshape(rows.size, 2 * dist.size)

    def stop_ahead(self, rows: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(A,) distance (m) along the recorded route of track ``rows`` from the progress point
        of positions (x, y) to the route's end where its driver stands there (0 at or past
        it), inf where the route does not end standing."""
        rows = np.asarray(rows, np.int64)
        if rows.size == 0:
            return np.zeros(0, np.float64)
        at = self._progress(rows, x, y)
        end = self.end_arc[rows]
        here = self.farc[rows, at]
        return np.where(np.isnan(end), np.inf, np.maximum(end - here, 0.0))

    def commands(self, rows: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(A, 3) float32 one-hot commands of agents on track ``rows`` at positions (x, y)."""
        rows = np.asarray(rows, np.int64)
        if rows.size == 0:
            return np.zeros((0, len(COMMANDS)), np.float32)
        at = self._progress(rows, x, y)
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
