"""Reference paths of many vehicles in one flat store: the polylines that route-relative control
(:mod:`magail_sumo.sim.tracking`) follows and the route look-ahead reads.

A path is a polyline in the scene frame (m) resampled at a fixed ``spacing`` (1 m by default)
along its arc length, so that projecting a position onto it is a nearest-point search over a
short window of points around the vehicle's last progress point (a hint kept per vehicle: a
route that passes the same place twice, a loop or a U-turn, is not confused with itself). All
paths live end to end in three 1-D arrays ``x, y, s`` (``s``: arc length from the path's start,
m); path ``r`` holds points ``start[r] .. start[r] + count[r] - 1``. Adding a path appends
(arrays grow by doubling), so a city's paths are added as its agents join. A fourth array,
``limit``, holds the speed limit (m/s) of the road at each point, from the segment the point
lies on (0: unknown), when the path was added with limits.

Frames and units: scene frame (SUMO's network frame in cities), metres, radians (CCW from +x).
Every query works on arrays over many vehicles at once; positions before a path's start are
clamped to it, and a position past its end projects onto the line of its last segment (arc
lengths beyond the path's length: how far the vehicle has overshot it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: default resampling spacing (m)
SPACING = 1.0
#: projection window around the hint: points behind, points ahead (at 40 m/s and 0.1-s steps a
#: vehicle moves 4 points per step)
WINDOW = (4, 48)
#: the stretch of path (m) over which :func:`tightest_radius` measures turns
TURN_ARC = 4.0


def resample(points: np.ndarray, spacing: float = SPACING) -> tuple[np.ndarray, np.ndarray]:
    """(K, 2) points of polyline ``points`` ((M, 2), m) equally spaced along its arc, at most
    ``spacing`` m apart, first and last point kept, and (K,) their arc lengths (m); repeated
    points dropped; a polyline of no length is one point."""
    p, s, _ = _resampled(points, None, spacing)
    return p, s


def _resampled(points: np.ndarray, values: np.ndarray | None, spacing: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`resample`, and ``values`` ((M,) one per point of ``points``, or None) carried
    to the resampled points: each takes the value of the input segment it lies on (the value
    of that segment's first point; the last point's on the last point)."""
    p = np.asarray(points, np.float64).reshape(-1, 2)
    finite = np.isfinite(p).all(axis=1)
    p = p[finite]
    v = None if values is None else np.asarray(values, np.float64).reshape(-1)[finite]
    if p.shape[0] == 0:
        raise ValueError("a path needs at least one finite point")
    seg = np.hypot(*np.diff(p, axis=0).T)
    keep = np.concatenate([[True], seg > 1e-9])
    p, seg = p[keep], seg[seg > 1e-9]
    if v is not None:  # a repeated point's value is the segment's that starts there
        v = v[np.concatenate([keep[1:], [True]])]
    if p.shape[0] == 1:
        return p, np.zeros(1), v
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(2, int(np.ceil(arc[-1] / spacing)) + 1)
    s = np.linspace(0.0, arc[-1], n)
    out = np.stack([np.interp(s, arc, p[:, 0]), np.interp(s, arc, p[:, 1])], axis=1)
    if v is not None:
        v = v[np.minimum(np.searchsorted(arc, s, side="right") - 1, p.shape[0] - 1)]
    return out, s, v


@dataclass(eq=False)
class Paths:
    """Paths end to end (module doc). ``n_paths`` / ``n_points`` are the used sizes."""

    x: np.ndarray
    y: np.ndarray
    s: np.ndarray
    start: np.ndarray
    count: np.ndarray
    n_paths: int = 0
    n_points: int = 0
    spacing: float = SPACING
    #: speed limit (m/s) at each point; 0: unknown (module doc)
    limit: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.limit is None:
            self.limit = np.zeros(self.x.shape[0])

    @classmethod
    def empty(cls, paths: int = 16, points: int = 1024, spacing: float = SPACING) -> "Paths":
        z = lambda n, dtype=np.float64: np.zeros(n, dtype)  # noqa: E731
        return cls(z(points), z(points), z(points), z(paths, np.int64), z(paths, np.int64),
                   spacing=float(spacing))

    @classmethod
    def of(cls, polylines, spacing: float = SPACING, limits=None) -> "Paths":
        """Paths of ``polylines`` (each (M, 2) m), rows in that order; ``limits``: each
        one's speed limits (:meth:`add`), or None."""
        out = cls.empty(max(1, len(polylines)), spacing=spacing)
        for i, p in enumerate(polylines):
            out.add(p, None if limits is None else limits[i])
        return out

    def __len__(self) -> int:
        return self.n_paths

    def add(self, points: np.ndarray, limits: np.ndarray | None = None) -> int:
        """Append the path of polyline ``points`` ((M, 2), m; resampled); its row.

        :param limits: (M,) the speed limit (m/s, 0: unknown) of the road from each point to
            the next; None: unknown throughout."""
        p, s, lim = _resampled(points, limits, self.spacing)
        k, m = self.n_points, p.shape[0]
        if k + m > self.x.shape[0]:
            size = max(k + m, 2 * self.x.shape[0])
            self.x, self.y, self.s, self.limit = (_grown(a, size) for a in
                                                  (self.x, self.y, self.s, self.limit))
        if self.n_paths == self.start.shape[0]:
            size = 2 * self.n_paths
            self.start, self.count = _grown(self.start, size), _grown(self.count, size)
        self.x[k:k + m], self.y[k:k + m], self.s[k:k + m] = p[:, 0], p[:, 1], s
        self.limit[k:k + m] = 0.0 if lim is None else np.where(np.isfinite(lim) & (lim > 0),
                                                               lim, 0.0)
        r = self.n_paths
        self.start[r], self.count[r] = k, m
        self.n_paths += 1
        self.n_points += m
        return r

    def length(self, rows: np.ndarray) -> np.ndarray:
        """(A,) length of paths ``rows`` (m)."""
        rows = np.asarray(rows, np.int64)
        return self.s[self.start[rows] + self.count[rows] - 1]

    def points(self, row: int) -> np.ndarray:
        """(K, 2) resampled points of path ``row``."""
        a, n = self.start[row], self.count[row]
        return np.stack([self.x[a:a + n], self.y[a:a + n]], axis=1)

    def project(self, rows: np.ndarray, x: np.ndarray, y: np.ndarray,
                hint: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Progress of vehicles at (x, y) on paths ``rows``: (A,) index (within the path) of
        the nearest resampled point and (A,) arc length (m) of the position's foot on the
        segments beside it. With ``hint`` ((A,) indices of the last progress point) only
        :data:`WINDOW` points around it are searched; without, the whole path."""
        rows = np.asarray(rows, np.int64)
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        if rows.size == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        cnt = self.count[rows]
        if hint is None:
            lo = np.zeros(rows.size, np.int64)
            width = int(cnt.max())
        else:
            lo = np.clip(np.asarray(hint, np.int64) - WINDOW[0], 0, None)
            width = WINDOW[0] + WINDOW[1] + 1
        idx = lo[:, None] + np.arange(width)[None, :]  # (A, W) within-path indices
        inside = idx < cnt[:, None]
        flat = self.start[rows][:, None] + np.minimum(idx, cnt[:, None] - 1)
        d2 = (self.x[flat] - x[:, None]) ** 2 + (self.y[flat] - y[:, None]) ** 2
        j = np.argmin(np.where(inside, d2, np.inf), axis=1)
        at = lo + j
        return at, self._foot(rows, at, x, y)

    def _foot(self, rows, at, x, y) -> np.ndarray:
        """(A,) arc length of the feet of (x, y) on the segments before and after point
        ``at`` (the nearer one; clamped to the path's start; past its end, the foot on the
        last segment's line, so a vehicle that overshoots a path's end is that far past it)."""
        base, cnt = self.start[rows], self.count[rows]
        best_s = self.s[base + at]
        best_d = np.hypot(self.x[base + at] - x, self.y[base + at] - y)
        for lo in (at - 1, at):  # the segment [lo, lo + 1]
            ok = (lo >= 0) & (lo + 1 < cnt)
            lo0 = np.maximum(lo, 0)  # (np.clip costs several µs a call on a few elements)
            a = base + lo0
            b = base + np.minimum(lo0 + 1, cnt - 1)
            ex, ey = self.x[b] - self.x[a], self.y[b] - self.y[a]
            ll = ex * ex + ey * ey
            u = np.maximum(((x - self.x[a]) * ex + (y - self.y[a]) * ey)
                           / np.where(ll > 0, ll, 1.0), 0.0)
            u = np.where(lo0 + 2 == cnt, u, np.minimum(u, 1.0))  # the last segment: on past
            px, py = self.x[a] + u * ex, self.y[a] + u * ey
            d = np.hypot(px - x, py - y)
            better = ok & (d < best_d)
            best_d = np.where(better, d, best_d)
            best_s = np.where(better, self.s[a] + u * np.sqrt(ll), best_s)
        return best_s

    def at(self, rows: np.ndarray, s: np.ndarray, extend: bool = False
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (x, y, m) and heading (rad) of paths ``rows`` at arc lengths ``s`` (m;
        broadcast: (A,) or (A, P)), clamped to the paths' ends; with ``extend``, past the
        end the path runs on straight along its last heading. A one-point path has heading
        0 at its point."""
        rows = np.asarray(rows, np.int64)
        s = np.asarray(s, np.float64)
        shape = s.shape
        s2 = s.reshape(rows.size, -1)
        base, cnt = self.start[rows][:, None], self.count[rows][:, None]
        step = self.s[base + cnt - 1] / np.maximum(cnt - 1, 1)  # points equally spaced in s
        u = np.maximum(s2 / np.where(step > 0, step, 1.0), 0.0)
        j = np.minimum(np.floor(u).astype(np.int64), np.maximum(cnt - 2, 0))
        a, b = base + j, base + np.minimum(j + 1, cnt - 1)
        seg = self.s[b] - self.s[a]
        frac = np.maximum(np.where(seg > 0, (s2 - self.s[a]) / np.where(seg > 0, seg, 1.0), 0.0),
                          0.0)
        if not extend:
            frac = np.minimum(frac, 1.0)
        px = self.x[a] + frac * (self.x[b] - self.x[a])
        py = self.y[a] + frac * (self.y[b] - self.y[a])
        heading = np.arctan2(self.y[b] - self.y[a], self.x[b] - self.x[a])
        return px.reshape(shape), py.reshape(shape), heading.reshape(shape)

    def ahead(self, rows: np.ndarray, s: np.ndarray, x: np.ndarray, y: np.ndarray,
              yaw: np.ndarray, distances) -> np.ndarray:
        """(A, 2·P) float32: for each of the P ``distances`` (m), the ego-frame x, y (m; +x
        along ``yaw``, +y to the left) of the path ``distance`` m past arc length ``s`` of
        vehicles at (x, y, yaw); the path's end where it ends sooner."""
        d = np.asarray(distances, np.float64)
        rows = np.asarray(rows, np.int64)
        if rows.size == 0:
            return np.zeros((0, 2 * d.size), np.float32)
        px, py, _ = self.at(rows, np.asarray(s, np.float64)[:, None] + d[None, :])
        dx, dy = px - np.asarray(x)[:, None], py - np.asarray(y)[:, None]
        c, sn = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        out = np.empty((rows.size, d.size, 2), np.float32)
        out[:, :, 0] = c * dx + sn * dy
        out[:, :, 1] = -sn * dx + c * dy
        return out.reshape(rows.size, 2 * d.size)

    def limits_ahead(self, rows: np.ndarray, at: np.ndarray, reach: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Speed limits of paths ``rows`` from progress points ``at`` ((A,) indices within
        each path) to ``reach`` m on: (A,) the limit at the progress point (m/s, 0: unknown),
        (A,) the lowest known limit ahead within reach (the limit here when none is lower) and
        (A,) how far ahead (m) it begins (0 when it is the limit here)."""
        rows = np.asarray(rows, np.int64)
        if rows.size == 0:
            z = np.zeros(0)
            return z, z, z
        base, cnt = self.start[rows], self.count[rows]
        at = np.clip(np.asarray(at, np.int64), 0, cnt - 1)
        k = at[:, None] + np.arange(int(np.ceil(reach / self.spacing)) + 1)[None, :]
        flat = base[:, None] + np.minimum(k, cnt[:, None] - 1)
        lim = np.where((k < cnt[:, None]) & (self.limit[flat] > 0), self.limit[flat], np.inf)
        here = self.limit[base + at]
        j = np.argmin(lim, axis=1)
        low = lim[np.arange(rows.size), j]
        lower = np.isfinite(low) & ((here <= 0) | (low < here))
        gap = self.s[flat[np.arange(rows.size), j]] - self.s[base + at]
        return (here, np.where(lower, low, here), np.where(lower, np.maximum(gap, 0.0), 0.0))

    def turn(self, rows: np.ndarray, s: np.ndarray, lookahead: float) -> np.ndarray:
        """(A,) heading change (rad, wrapped, CCW positive) of paths ``rows`` between arc
        length ``s`` and ``lookahead`` m further (the path's end when nearer)."""
        s = np.asarray(s, np.float64)
        _, _, h0 = self.at(rows, s)
        _, _, h1 = self.at(rows, s + lookahead)
        return (h1 - h0 + np.pi) % (2 * np.pi) - np.pi


def tightest_turn(points: np.ndarray, arc: float = TURN_ARC) -> tuple[float, float]:
    """The tightest turn of polyline ``points`` ((M, 2), m): its radius (m) and the arc
    length (m) where it begins. Over every stretch of ``arc`` m (resampled at 0.5 m) the
    radius is the stretch's length over its heading change, ``arc / |Δθ|``; the least of them
    (inf, 0 for a straight path or one shorter than ``arc``). A turn held over the stretch reads
    its radius; a kink between two lane shapes spreads over the stretch and reads wide. SUMO's
    on-the-spot turnaround (a half circle of about 1.6 m between the two directions' lane
    centres) reads 1.3-1.6 m."""
    p, s = resample(points, 0.5)
    k = int(round(arc / 0.5))
    if p.shape[0] < 3 or p.shape[0] - 1 <= k:
        return float("inf"), 0.0
    heading = np.unwrap(np.arctan2(*np.diff(p, axis=0)[:, ::-1].T))
    turn = np.abs(heading[k:] - heading[:-k])
    i = int(turn.argmax())
    return (float(arc / turn[i]), float(s[i])) if turn[i] > 1e-9 else (float("inf"), 0.0)


def _grown(a: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros(n, a.dtype)
    out[:a.shape[0]] = a
    return out
