"""Vectorised 2-D ray casting: many rays against many line segments in one numpy pass.

Frames: everything in the scene frame (metres). A ray starts at an origin and points along an
angle (radians, counter-clockwise from +x); its reading is the distance to the first segment it
hits, or ``max_range`` when it hits nothing within range.

The work is split in two steps so that only nearby geometry is intersected:
:func:`candidate_pairs` keeps the (ray group, segment) pairs whose segment comes within
``max_range`` of the group's origin, then :func:`cast` intersects each group's rays with its
candidate segments only.
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-12


def box_edges(center: np.ndarray, half_extent: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """The 4 edges of oriented boxes.

    :param center: (N, 2) box centres.
    :param half_extent: (N, 2) half length (along heading) and half width.
    :param heading: (N,) box yaw in radians.
    :returns: (N, 4, 2, 2) edges as (start, end) points.
    """
    c, s = np.cos(heading), np.sin(heading)
    fwd = np.stack([c, s], axis=-1) * half_extent[:, :1]
    left = np.stack([-s, c], axis=-1) * half_extent[:, 1:2]
    corners = np.stack([center + fwd + left, center - fwd + left, center - fwd - left,
                        center + fwd - left], axis=1)  # (N, 4, 2), counter-clockwise
    return np.stack([corners, np.roll(corners, -1, axis=1)], axis=2)


def point_segment_distance(points: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray) -> np.ndarray:
    """Euclidean distance from points to segments, broadcasting (..., 2) arrays."""
    e = seg_end - seg_start
    w = points - seg_start
    t = np.clip(np.sum(w * e, axis=-1) / np.maximum(np.sum(e * e, axis=-1), _EPS), 0.0, 1.0)
    return np.linalg.norm(w - t[..., None] * e, axis=-1)


def candidate_pairs(origins: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray,
                    max_range: float, chunk: int = 1 << 22) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (group index, segment index) whose segment lies within ``max_range`` of the origin.

    :param origins: (A, 2) ray-group origins.
    :param seg_start, seg_end: (S, 2) segment end points.
    :returns: two (K,) int arrays, sorted by group.
    """
    a, s = origins.shape[0], seg_start.shape[0]
    if a == 0 or s == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    # cheap bounding-box test first, exact distance on the survivors
    lo = np.minimum(seg_start, seg_end) - max_range
    hi = np.maximum(seg_start, seg_end) + max_range
    groups, segs = [], []
    step = max(1, chunk // s)
    for i0 in range(0, a, step):
        o = origins[i0:i0 + step, None, :]
        inside = np.all((o >= lo) & (o <= hi), axis=-1)
        gi, si = np.nonzero(inside)
        if gi.size:
            d = point_segment_distance(origins[i0 + gi], seg_start[si], seg_end[si])
            keep = d <= max_range
            groups.append(gi[keep] + i0)
            segs.append(si[keep])
    if not groups:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(groups).astype(np.int64), np.concatenate(segs).astype(np.int64)


def cast(origins: np.ndarray, angles: np.ndarray, max_range: float, seg_start: np.ndarray,
         seg_end: np.ndarray, pair_group: np.ndarray, pair_seg: np.ndarray) -> np.ndarray:
    """Distances along rays to the nearest candidate segment.

    :param origins: (A, 2) origin of each ray group.
    :param angles: (A, B) ray angles in radians (scene frame).
    :param max_range: reading when nothing is hit (metres).
    :param seg_start, seg_end: (S, 2) segments.
    :param pair_group, pair_seg: (K,) candidate pairs from :func:`candidate_pairs`.
    :returns: (A, B) float64 distances in [0, max_range].
    """
    a, b = angles.shape
    out = np.full((a, b), float(max_range))
    if pair_group.size == 0 or b == 0:
        return out
    d = np.stack([np.cos(angles), np.sin(angles)], axis=-1)  # (A, B, 2)
    p = seg_start[pair_seg] - origins[pair_group]  # (K, 2) segment start relative to origin
    e = seg_end[pair_seg] - seg_start[pair_seg]  # (K, 2)
    dk = d[pair_group]  # (K, B, 2)
    denom = dk[..., 0] * e[:, None, 1] - dk[..., 1] * e[:, None, 0]  # cross(D, E)
    t_num = p[:, None, 0] * e[:, None, 1] - p[:, None, 1] * e[:, None, 0]  # cross(P, E)
    u_num = p[:, None, 0] * dk[..., 1] - p[:, None, 1] * dk[..., 0]  # cross(P, D)
    ok = np.abs(denom) > _EPS
    safe = np.where(ok, denom, 1.0)
    t = t_num / safe
    u = u_num / safe
    hit = ok & (t >= 0.0) & (u >= 0.0) & (u <= 1.0)
    # parallel, overlapping segments: the ray reaches the nearer end point of the segment
    coll = ~ok & (np.abs(u_num) <= 1e-9)
    if np.any(coll):
        proj_s = p[:, None, 0] * dk[..., 0] + p[:, None, 1] * dk[..., 1]
        q = p + e
        proj_e = q[:, None, 0] * dk[..., 0] + q[:, None, 1] * dk[..., 1]
        lo = np.minimum(proj_s, proj_e)
        hi = np.maximum(proj_s, proj_e)
        t_coll = np.where(lo >= 0.0, lo, np.where(hi >= 0.0, 0.0, np.inf))
        t = np.where(coll, t_coll, t)
        hit |= coll & np.isfinite(t_coll)
    t = np.where(hit & (t <= max_range), t, max_range)
    np.minimum.at(out, pair_group, t)
    return out
