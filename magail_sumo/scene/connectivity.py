"""Lane connectivity inferred from geometry, for maps recorded without any (nuScenes, Lyft...).

One vectorised pass over all lanes (pairwise L × L arrays; real maps have at most a few
thousand lanes):

* successor: lane ``b`` follows lane ``a`` when ``a``'s last point lies within
  :data:`MAX_GAP` of ``b``'s first point and the heading of ``a``'s last segment differs from
  that of ``b``'s first segment by at most :data:`MAX_ANGLE_DEG`;
* neighbour: lane ``b`` is a left (right) neighbour of ``a`` when, at ``a``'s middle point,
  ``b``'s middle point lies :data:`MIN_OFFSET`..:data:`MAX_OFFSET` to the left (right), the two
  middle headings differ by at most :data:`MAX_ANGLE_DEG`, and the lanes overlap along ``a``
  for at least half the shorter lane; the nearest such lane on each side is kept and the
  neighbour spans both whole lanes.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .roadmap import Lane, LaneNeighbor

MAX_GAP = 1.5  #: m between a lane's end and its successor's start
MAX_ANGLE_DEG = 30.0  #: heading difference of connected or neighbouring lanes
MIN_OFFSET, MAX_OFFSET = 1.5, 5.0  #: m, lateral offset of a neighbour's middle point


def _wrap(angle: np.ndarray) -> np.ndarray:
    return np.abs((angle + np.pi) % (2 * np.pi) - np.pi)


def infer_lane_connectivity(lanes: tuple[Lane, ...] | list[Lane], *, successors: bool = True,
                            neighbors: bool = True) -> tuple[tuple[Lane, ...], int, int]:
    """``(lanes with inferred links, successor links, neighbour links)``.

    ``successors`` / ``neighbors``: which kinds of link to infer.
    Links are added to lanes' ``entry_lanes``/``exit_lanes`` and ``left_neighbors``/
    ``right_neighbors`` (existing ones are kept; call it for maps with none). Lanes with fewer
    than two distinct points get no links.
    """
    lanes = tuple(lanes)
    n_lanes = len(lanes)
    if n_lanes < 2:
        return lanes, 0, 0
    sizes = np.fromiter((l.polyline.shape[0] for l in lanes), np.int64, n_lanes)
    pts = np.concatenate([l.polyline[:, :2] for l in lanes])
    first = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    last = first + sizes - 1
    usable = sizes >= 2
    # per-lane arc length over the concatenated points (segments between lanes zeroed)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    seg[last[:-1]] = 0.0
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    length = cum[last] - cum[first]
    usable &= length > 0.1

    def heading(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        d = pts[b] - pts[a]
        return np.arctan2(d[:, 1], d[:, 0])

    safe_next = np.minimum(first + 1, last)
    safe_prev = np.maximum(last - 1, first)
    h_start, h_end = heading(first, safe_next), heading(safe_prev, last)
    start, end = pts[first], pts[last]
    max_angle = np.radians(MAX_ANGLE_DEG)
    ok = usable[:, None] & usable[None, :] & ~np.eye(n_lanes, dtype=bool)

    gap = np.linalg.norm(end[:, None, :] - start[None, :, :], axis=2)
    succ = successors & ok & (gap <= MAX_GAP) & (_wrap(h_end[:, None] - h_start[None, :]) <= max_angle)

    mid = first + (sizes - 1) // 2
    m_prev, m_next = np.maximum(mid - 1, first), np.minimum(mid + 1, last)
    h_mid = heading(m_prev, m_next)
    direction = np.stack([np.cos(h_mid), np.sin(h_mid)], axis=1)
    d = pts[mid][None, :, :] - pts[mid][:, None, :]  # [a, b]: b's middle relative to a's
    lat = direction[:, None, 0] * d[..., 1] - direction[:, None, 1] * d[..., 0]
    lon = np.einsum("ak,abk->ab", direction, d)
    overlap = 0.5 * (length[:, None] + length[None, :]) - np.abs(lon)
    near = neighbors & ok & (_wrap(h_mid[:, None] - h_mid[None, :]) <= max_angle) \
        & (np.abs(lat) >= MIN_OFFSET) & (np.abs(lat) <= MAX_OFFSET) \
        & (overlap >= 0.5 * np.minimum(length[:, None], length[None, :]))
    big = np.inf
    left = np.where(near & (lat > 0), np.abs(lat), big)
    right = np.where(near & (lat < 0), np.abs(lat), big)
    left_of, right_of = left.argmin(axis=1), right.argmin(axis=1)
    has_left = left[np.arange(n_lanes), left_of] < big
    has_right = right[np.arange(n_lanes), right_of] < big

    ids = [l.id for l in lanes]
    out = []
    for a, lane in enumerate(lanes):  # builds the frozen records; the geometry is done above
        exits = tuple(ids[b] for b in np.flatnonzero(succ[a]))
        entries = tuple(ids[b] for b in np.flatnonzero(succ[:, a]))

        def nb(b: int) -> LaneNeighbor:
            return LaneNeighbor(ids[b], 0, int(sizes[a]) - 1, 0, int(sizes[b]) - 1)

        out.append(dataclasses.replace(
            lane,
            entry_lanes=lane.entry_lanes + tuple(i for i in entries if i not in lane.entry_lanes),
            exit_lanes=lane.exit_lanes + tuple(i for i in exits if i not in lane.exit_lanes),
            left_neighbors=lane.left_neighbors + ((nb(int(left_of[a])),) if has_left[a] else ()),
            right_neighbors=lane.right_neighbors + ((nb(int(right_of[a])),) if has_right[a] else ()),
        ))
    return tuple(out), int(succ.sum()), int(has_left.sum() + has_right.sum())
