"""Lane connectivity inferred from geometry, for maps recorded without any (nuScenes, Lyft...).

Vectorised over all lanes (pairwise arrays, computed in blocks of rows so memory stays
O(block × L)):

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
#: most lanes a map may have for inference (pairwise work grows with the square; real maps
#: cut to a scene have a few hundred to a few thousand lanes)
MAX_LANES = 5_000
_BLOCK = 128  #: lanes per block of pairwise rows


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
    all_lanes = tuple(lanes)
    lanes = tuple(l for l in all_lanes if l.polyline.shape[0] >= 2)
    n_lanes = len(lanes)
    if n_lanes < 2 or not (successors or neighbors):
        return all_lanes, 0, 0
    sizes = np.fromiter((l.polyline.shape[0] for l in lanes), np.int64, n_lanes)
    pts = np.concatenate([l.polyline[:, :2] for l in lanes])
    first = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    last = first + sizes - 1
    usable = np.ones(n_lanes, bool)
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
    mid = first + (sizes - 1) // 2
    h_mid = heading(np.maximum(mid - 1, first), np.minimum(mid + 1, last))
    direction = np.stack([np.cos(h_mid), np.sin(h_mid)], axis=1)
    mids = pts[mid]
    succ_a: list[np.ndarray] = []
    succ_b: list[np.ndarray] = []
    left_of = np.zeros(n_lanes, np.int64)
    right_of = np.zeros(n_lanes, np.int64)
    has_left = np.zeros(n_lanes, bool)
    has_right = np.zeros(n_lanes, bool)
    cols = np.arange(n_lanes)
    for lo in range(0, n_lanes, _BLOCK):  # rows in blocks: memory O(block × L), not O(L²)
        rows = np.arange(lo, min(lo + _BLOCK, n_lanes))
        ok = usable[rows, None] & usable[None, :] & (rows[:, None] != cols[None, :])
        if successors:
            gap = np.linalg.norm(end[rows, None, :] - start[None, :, :], axis=2)
            succ = ok & (gap <= MAX_GAP) & (_wrap(h_end[rows, None] - h_start[None, :]) <= max_angle)
            a, b = np.nonzero(succ)
            succ_a.append(rows[a])
            succ_b.append(b)
        if neighbors:
            d = mids[None, :, :] - mids[rows, None, :]  # [a, b]: b's middle relative to a's
            dr = direction[rows]
            lat = dr[:, None, 0] * d[..., 1] - dr[:, None, 1] * d[..., 0]
            lon = np.einsum("ak,abk->ab", dr, d)
            la = length[rows, None]
            near = ok & (_wrap(h_mid[rows, None] - h_mid[None, :]) <= max_angle) \
                & (np.abs(lat) >= MIN_OFFSET) & (np.abs(lat) <= MAX_OFFSET) \
                & (0.5 * (la + length[None, :]) - np.abs(lon) >= 0.5 * np.minimum(la, length[None, :]))
            for side, of, has in ((lat > 0, left_of, has_left), (lat < 0, right_of, has_right)):
                dist = np.where(near & side, np.abs(lat), np.inf)
                best = dist.argmin(axis=1)
                of[rows] = best
                has[rows] = np.isfinite(dist[np.arange(rows.size), best])
    pairs_a = np.concatenate(succ_a) if succ_a else np.zeros(0, np.int64)
    pairs_b = np.concatenate(succ_b) if succ_b else np.zeros(0, np.int64)
    exits_of: list[list[int]] = [[] for _ in range(n_lanes)]
    entries_of: list[list[int]] = [[] for _ in range(n_lanes)]

    ids = [l.id for l in lanes]
    out: dict[int, Lane] = {}
    for a, b in zip(pairs_a.tolist(), pairs_b.tolist()):
        exits_of[a].append(ids[b])
        entries_of[b].append(ids[a])
    for a, lane in enumerate(lanes):  # builds the frozen records; the geometry is done above
        exits, entries = exits_of[a], entries_of[a]

        def nb(b: int) -> LaneNeighbor:
            return LaneNeighbor(ids[b], 0, int(sizes[a]) - 1, 0, int(sizes[b]) - 1)

        out[id(lane)] = dataclasses.replace(
            lane,
            entry_lanes=lane.entry_lanes + tuple(i for i in entries if i not in lane.entry_lanes),
            exit_lanes=lane.exit_lanes + tuple(i for i in exits if i not in lane.exit_lanes),
            left_neighbors=lane.left_neighbors + ((nb(int(left_of[a])),) if has_left[a] else ()),
            right_neighbors=lane.right_neighbors + ((nb(int(right_of[a])),) if has_right[a] else ()),
        )
    return (tuple(out.get(id(l), l) for l in all_lanes), int(pairs_a.size),
            int(has_left.sum() + has_right.sum()))


def link_isolated_lanes(lanes: tuple[Lane, ...] | list[Lane]) -> tuple[tuple[Lane, ...], int]:
    """``(lanes, successor links added)``: lanes recorded with neither entry nor exit lanes in
    a map that has links elsewhere (the link lists were lost: seen in MetaDrive and MetaVQA
    pickles, on signalled junction lanes whose ends meet other lanes' exactly) get the
    successor links :func:`infer_lane_connectivity` finds to and from them; every other link
    stays as recorded."""
    all_lanes = tuple(lanes)
    isolated = {l.id for l in all_lanes if not l.entry_lanes and not l.exit_lanes}
    if not isolated or len(isolated) == len(all_lanes) or len(all_lanes) > MAX_LANES:
        return all_lanes, 0
    inferred, _, _ = infer_lane_connectivity(all_lanes, successors=True, neighbors=False)
    out, added = [], 0
    for old, new in zip(all_lanes, inferred):
        mine = old.id in isolated
        entries = old.entry_lanes + tuple(i for i in new.entry_lanes
                                          if i not in old.entry_lanes and (mine or i in isolated))
        exits = old.exit_lanes + tuple(i for i in new.exit_lanes
                                       if i not in old.exit_lanes and (mine or i in isolated))
        added += len(exits) - len(old.exit_lanes)
        out.append(dataclasses.replace(old, entry_lanes=entries, exit_lanes=exits)
                   if (entries, exits) != (old.entry_lanes, old.exit_lanes) else old)
    return tuple(out), added
