"""Nearest-lane queries over all agents of a step (numba kernel over a :class:`SegmentGrid`).

Frames: scene frame, metres, radians CCW from +x. Lane centre lines are split into segments
owned by a lane index (position of the lane in ``RoadMap.lanes``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from magail_sumo.scene import Lane

from .raycast import SegmentGrid, cell_gap, indexed_polyline_segments


@dataclass(frozen=True)
class LaneQuery:
    """Per-point result of :meth:`LaneIndex.query` (A = number of points).

    :param lane: (A,) index of the nearest lane whose direction is within 90° of the query
        heading (-1 when none lies within the grid cell size: the same answer wherever the
        grid's cells fall).
    :param lateral: (A,) signed distance to that lane's centre line (m, positive = the point
        lies left of the lane direction); 0 when ``lane`` is -1.
    :param heading_error: (A,) query heading minus lane direction, wrapped to [-pi, pi) (rad).
    :param distance: (A,) distance to the nearest lane centre line of any direction (m),
        capped at the grid cell size.
    """

    lane: np.ndarray
    lateral: np.ndarray
    heading_error: np.ndarray
    distance: np.ndarray


#: squared distances (m²) this close count as a tie between two lane segments
_TIE = 1e-9


#: grid cells per search radius of a :class:`LaneIndex`: a query visits only the cells that
#: come within the radius of its point (fewer segments than the 3 x 3 radius-sized cells
#: around it: 0.39 s against 0.46 s for 390k real points; 3, 4 and 6 per radius were no faster);
#: which segments count, and so every answer, does not depend on it
GRID_SPLIT = 2


@numba.njit(cache=True)
def _nearest(px, py, yaw, starts, ends, owner, x0, y0, cell, nx, ny, offsets, items, radius):
    a = px.shape[0]
    lane = np.full(a, -1, np.int64)
    lateral = np.zeros(a)
    herr = np.zeros(a)
    dist = np.full(a, radius)
    r2 = radius * radius
    reach = int(np.ceil(radius / cell))
    for i in range(a):
        ox, oy = px[i], py[i]
        ch, sh = np.cos(yaw[i]), np.sin(yaw[i])
        fx = (ox - x0) / cell
        fy = (oy - y0) / cell
        cx = int(np.floor(fx))
        cy = int(np.floor(fy))
        best_any = r2
        best_al = np.inf
        best_k = -1
        for gx in range(max(cx - reach, 0), min(cx + reach + 1, nx)):
            dx = cell_gap(gx, cx, fx, cell)
            for gy in range(max(cy - reach, 0), min(cy + reach + 1, ny)):
                dy = cell_gap(gy, cy, fy, cell)
                if dx * dx + dy * dy >= r2:  # no point of the cell within the radius
                    continue
                c = gx * ny + gy
                for m in range(offsets[c], offsets[c + 1]):
                    k = items[m]
                    ax, ay = starts[k, 0], starts[k, 1]
                    ex, ey = ends[k, 0] - ax, ends[k, 1] - ay
                    wx, wy = ox - ax, oy - ay
                    ll = ex * ex + ey * ey
                    t = 0.0 if ll < 1e-12 else min(1.0, max(0.0, (wx * ex + wy * ey) / ll))
                    qx, qy = wx - t * ex, wy - t * ey
                    d2 = qx * qx + qy * qy
                    if d2 < best_any:
                        best_any = d2
                    # within the radius only (every segment that close lies in a visited
                    # cell: a segment is listed in every cell its bounding box overlaps); of
                    # (near) ties (the two segments at a vertex) the lower segment wins,
                    # whatever the visit order (a segment in several cells may come again)
                    if ll < 1e-12 or d2 >= r2 or d2 > best_al + _TIE or \
                            (d2 >= best_al - _TIE and k > best_k):
                        continue
                    if ex * ch + ey * sh <= 0.0:  # lane runs against the heading
                        continue
                    best_al = d2
                    best_k = k
                    n = np.sqrt(ll)
                    lane[i] = owner[k]
                    lateral[i] = (ex * wy - ey * wx) / n
                    herr[i] = (yaw[i] - np.arctan2(ey, ex) + np.pi) % (2 * np.pi) - np.pi
        dist[i] = np.sqrt(best_any)
    return lane, lateral, herr, dist


@dataclass(frozen=True)
class LaneIndex:
    """Lane centre-line segments of a scene indexed in a grid, built once per scene.

    :param cell: the search radius (m) of :meth:`build`: distances beyond it are reported as
        ``cell``; the grid's cells are :data:`GRID_SPLIT` times smaller.
    """

    grid: SegmentGrid
    owner: np.ndarray  # (S,) lane index of each grid segment
    ids: np.ndarray  # (L,) WOMD lane id of each lane index
    radius: float  # m, the search radius (``cell`` of :meth:`build`)

    @classmethod
    def build(cls, lanes: tuple[Lane, ...], cell: float = 10.0) -> "LaneIndex":
        starts, ends, owner = indexed_polyline_segments([l.polyline for l in lanes])
        return cls(SegmentGrid.build(starts, ends, cell / GRID_SPLIT), owner,
                   np.array([l.id for l in lanes], np.int64), float(cell))

    def query(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> LaneQuery:
        """Nearest lanes of A points with headings (all arrays (A,))."""
        g = self.grid
        f64 = lambda v: np.ascontiguousarray(v, np.float64)  # noqa: E731
        lane, lat, herr, dist = _nearest(f64(x), f64(y), f64(yaw), g.starts, g.ends, self.owner,
                                         g.x0, g.y0, g.cell, g.nx, g.ny, g.offsets, g.items,
                                         self.radius)
        return LaneQuery(lane, lat, herr, dist)
