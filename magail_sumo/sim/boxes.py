"""Oriented boxes in the plane: corners and signed distance between two boxes.

Pure array functions on broadcast arrays. Frame: 2-D scene frame, metres; a box is its centre
``(x, y)``, heading (radians, CCW from +x, along its length), length and width. Used by the
sensors (:mod:`magail_sumo.sensors.raycast`), the realism metric
(:mod:`magail_sumo.evaluation.realism.interaction`) and the converter's quality run
(:mod:`converters.sumo.baseline`).
"""

from __future__ import annotations

import numpy as np

_SIGNS = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], np.float32)  # CCW corners


def box_corners(x: np.ndarray, y: np.ndarray, heading: np.ndarray, length: np.ndarray,
                width: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corner coordinates ``(..., 4)`` each for x and y, counter-clockwise from front-left."""
    c, s = np.cos(heading)[..., None], np.sin(heading)[..., None]
    lx = _SIGNS[:, 0] * (length[..., None] / 2)
    ly = _SIGNS[:, 1] * (width[..., None] / 2)
    return x[..., None] + c * lx - s * ly, y[..., None] + s * lx + c * ly


def rect_vertex_distance(px: np.ndarray, py: np.ndarray, cx: np.ndarray, cy: np.ndarray,
                         c: np.ndarray, s: np.ndarray, hl: np.ndarray, hw: np.ndarray
                         ) -> np.ndarray:
    """Distance from points to rectangles (0 inside); points carry a trailing axis of 4."""
    dx, dy = px - cx[..., None], py - cy[..., None]
    u = np.abs(c[..., None] * dx + s[..., None] * dy) - hl[..., None]
    v = np.abs(-s[..., None] * dx + c[..., None] * dy) - hw[..., None]
    u, v = np.maximum(u, 0), np.maximum(v, 0)
    return np.sqrt(u * u + v * v).min(-1)


def signed_box_distance(xa, ya, ha, la, wa, xb, yb, hb, lb, wb) -> np.ndarray:
    """Signed distance between rectangles A and B (broadcast arrays): the gap when apart,
    minus the penetration depth (smallest overlap over the four edge axes) when overlapping."""
    ca, sa, cb, sb = np.cos(ha), np.sin(ha), np.cos(hb), np.sin(hb)
    hla, hwa, hlb, hwb = la / 2, wa / 2, lb / 2, wb / 2
    dx, dy = xb - xa, yb - ya
    # separating-axis overlaps on A's and B's axes
    cab = np.abs(ca * cb + sa * sb)  # |cos(hb - ha)|
    sab = np.abs(sa * cb - ca * sb)  # |sin(hb - ha)|
    pen = np.minimum.reduce([
        hla + hlb * cab + hwb * sab - np.abs(ca * dx + sa * dy),
        hwa + hlb * sab + hwb * cab - np.abs(-sa * dx + ca * dy),
        hlb + hla * cab + hwa * sab - np.abs(cb * dx + sb * dy),
        hwb + hla * sab + hwa * cab - np.abs(-sb * dx + cb * dy),
    ])
    # gap: nearest vertex of one rectangle to the other
    axs, ays = box_corners(xa, ya, ha, la, wa)
    bxs, bys = box_corners(xb, yb, hb, lb, wb)
    gap = np.minimum(rect_vertex_distance(axs, ays, xb, yb, cb, sb, hlb, hwb),
                     rect_vertex_distance(bxs, bys, xa, ya, ca, sa, hla, hwa))
    return np.where(pen > 0, -pen, gap)
