"""Top-down RGB frames of a scene with numpy only: lanes, road lines, road edges and boxes.

The view is a fixed axis-aligned window of the scene frame (m), +y up in the image.
"""

from __future__ import annotations

import numpy as np

from magail_sumo.scene import Scene
from magail_sumo.sensors.raycast import polyline_segments

BACKGROUND = (30, 30, 30)
LANE, LINE, EDGE = (80, 80, 80), (200, 180, 60), (230, 230, 230)
AGENT, OTHER, LOG_ONLY = (60, 200, 90), (70, 130, 230), (170, 170, 170)


class TopDownRenderer:
    """Rasterises the static map once; :meth:`frame` adds boxes.

    :param bounds: (xmin, ymin, xmax, ymax) of the window (m, scene frame).
    :param size: (height, width) in pixels.
    """

    def __init__(self, scene: Scene, bounds: tuple[float, float, float, float],
                 size: tuple[int, int] = (512, 512)) -> None:
        self.h, self.w = size
        x0, y0, x1, y1 = bounds
        self.scale = min(self.w / max(x1 - x0, 1e-6), self.h / max(y1 - y0, 1e-6))  # px per m
        self.origin = (x0, y1)
        img = np.empty((self.h, self.w, 3), np.uint8)
        img[:] = BACKGROUND
        rm = scene.roadmap
        for polys, colour in (([l.polyline for l in rm.lanes], LANE),
                              ([l.polyline for l in rm.road_lines], LINE),
                              ([e.polyline for e in rm.road_edges], EDGE)):
            self._segments(img, *polyline_segments(polys), colour)
        self.base = img

    def _pixels(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        col = ((xy[:, 0] - self.origin[0]) * self.scale).astype(np.int64)
        row = ((self.origin[1] - xy[:, 1]) * self.scale).astype(np.int64)
        ok = (col >= 0) & (col < self.w) & (row >= 0) & (row < self.h)
        return row[ok], col[ok]

    def _segments(self, img: np.ndarray, starts: np.ndarray, ends: np.ndarray,
                  colour: tuple[int, int, int]) -> None:
        if not len(starts):
            return
        n = np.maximum(np.ceil(np.hypot(*(ends - starts).T) * self.scale * 2).astype(np.int64), 1) + 1
        seg = np.repeat(np.arange(len(starts)), n)
        u = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n - 1, n)
        pts = starts[seg] + u[:, None] * (ends[seg] - starts[seg])
        img[self._pixels(pts)] = colour

    def frame(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray,
              width: np.ndarray, colours: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 frame with filled boxes ((N,) arrays; (N, 3) uint8 colours)."""
        img = self.base.copy()
        if not len(x):
            return img
        k = max(int(np.ceil(float(np.max(length)) * self.scale)) * 2, 4)
        u = np.linspace(-0.5, 0.5, k)
        gu, gv = (g.reshape(-1) for g in np.meshgrid(u, u))
        c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        lu, wv = length[:, None] * gu[None], width[:, None] * gv[None]
        px = x[:, None] + c * lu - s * wv
        py = y[:, None] + s * lu + c * wv
        pts = np.stack([px.reshape(-1), py.reshape(-1)], axis=1)
        col = np.repeat(np.asarray(colours, np.uint8), gu.shape[0], axis=0)
        cr = ((pts[:, 0] - self.origin[0]) * self.scale).astype(np.int64)
        rr = ((self.origin[1] - pts[:, 1]) * self.scale).astype(np.int64)
        ok = (cr >= 0) & (cr < self.w) & (rr >= 0) & (rr < self.h)
        img[rr[ok], cr[ok]] = col[ok]
        return img
