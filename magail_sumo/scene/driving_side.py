"""Which side of the road traffic keeps to, from the lane map alone.

On a two-way road the lane carrying the opposite direction lies to the driver's left where
traffic keeps right (WOMD's US cities, Boston) and to the driver's right where it keeps left
(Singapore, the UK, Japan). :func:`driving_side` samples every lane centre line (not the
interpolating junction lanes) every :data:`STEP` m, and for each lane's middle sample finds the
nearest sample of another lane running the other way (heading difference over 150°) beside it
(within :data:`ALONG` m along the lane, :data:`MIN_LATERAL`–:data:`MAX_LATERAL` m across): that
lane's side is one vote. The side with at least :data:`SHARE` of at least :data:`MIN_VOTES`
votes wins; otherwise the map does not say (one-way streets only, a car park).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .roadmap import RoadMap

STEP = 4.0  #: resampling step along lanes (m)
ALONG, MIN_LATERAL, MAX_LATERAL = 6.0, 1.5, 12.0  #: the window an opposing lane is looked for
MIN_VOTES, SHARE = 5, 0.8
_ANTIPARALLEL = -0.866  #: cos 150°


@dataclass(frozen=True)
class DrivingSide:
    """:param side: ``"right"``, ``"left"`` or None (the map does not say).
    :param right_votes, left_votes: lanes whose opposing lane lies on the driver's left
        (traffic keeps right) / right."""

    side: str | None
    right_votes: int
    left_votes: int

    def to_dict(self) -> dict:
        return {"side": self.side, "votes": {"right": self.right_votes, "left": self.left_votes}}


def _samples(polyline: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points every :data:`STEP` m along a polyline and the unit direction there."""
    xy = np.asarray(polyline, np.float64)[:, :2]
    seg = np.diff(xy, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    keep = length > 1e-6
    seg, length = seg[keep], length[keep]
    if not length.size:
        return np.zeros((0, 2)), np.zeros((0, 2))
    start = np.concatenate([[0.0], np.cumsum(length)])
    s = np.arange(STEP / 2, start[-1], STEP) if start[-1] > STEP else np.array([start[-1] / 2])
    k = np.clip(np.searchsorted(start, s, side="right") - 1, 0, length.size - 1)
    origin = xy[:-1][keep]
    direction = seg / length[:, None]
    return origin[k] + direction[k] * (s - start[k])[:, None], direction[k]


def driving_side(roadmap: RoadMap) -> DrivingSide:
    """The side traffic keeps to on this map (module doc)."""
    pts, dirs, owner, middle = [], [], [], []
    for i, lane in enumerate(l for l in roadmap.lanes if not l.interpolating):
        p, d = _samples(lane.polyline)
        if not len(p):
            continue
        middle.append(sum(len(x) for x in pts) + len(p) // 2)
        pts.append(p)
        dirs.append(d)
        owner.append(np.full(len(p), i))
    if not pts:
        return DrivingSide(None, 0, 0)
    p, d, o = np.concatenate(pts), np.concatenate(dirs), np.concatenate(owner)
    right = left = 0
    for chunk in np.array_split(np.asarray(middle), max(1, len(middle) // 256)):
        q, qd = p[chunk], d[chunk]
        v = p[None] - q[:, None]  # (Q, M, 2)
        along = v[..., 0] * qd[:, None, 0] + v[..., 1] * qd[:, None, 1]
        lateral = qd[:, None, 0] * v[..., 1] - qd[:, None, 1] * v[..., 0]  # + : on the left
        opposite = (d[None, :, 0] * qd[:, None, 0] + d[None, :, 1] * qd[:, None, 1]) \
            < _ANTIPARALLEL
        ok = opposite & (o[None] != o[chunk][:, None]) & (np.abs(along) < ALONG) \
            & (np.abs(lateral) > MIN_LATERAL) & (np.abs(lateral) < MAX_LATERAL)
        dist = np.where(ok, np.hypot(along, lateral), np.inf)
        best = np.argmin(dist, axis=1)
        found = np.isfinite(dist[np.arange(len(chunk)), best])
        side = lateral[np.arange(len(chunk)), best][found]
        right += int((side > 0).sum())
        left += int((side < 0).sum())
    total = right + left
    if total < MIN_VOTES:
        return DrivingSide(None, right, left)
    if right >= SHARE * total:
        return DrivingSide("right", right, left)
    if left >= SHARE * total:
        return DrivingSide("left", right, left)
    return DrivingSide(None, right, left)
