"""Red-light violations: an object crosses the stop line of the lane it is on while that lane's
signal is red (STOP or ARROW_STOP).

The WOSAC rule (the realism metrics' ``traffic_light_violation``,
:mod:`magail_sumo.evaluation.realism`), kept with the scene model because it reads nothing but a
scene: the recorded data's signal check (:mod:`.signal_sanity`, in ``conversion.json`` and
``inspect``) uses it too.

Replicates the official definition exactly, including its peculiarities: lanes are padded to a
common point count with (0, 0) points, a segment counts when its start point is real (so a
shorter lane gets an extra segment from its last point to the origin), and the nearest-segment
search measures ``|(q - A) + t (B - A)|`` (a plus where a minus would be expected).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from magail_sumo.scene import Scene
from magail_sumo.scene.types import LaneType, SignalState

_FAR = np.float32(1e10)
_STOP_STATES = (int(SignalState.ARROW_STOP), int(SignalState.STOP))


@dataclass(frozen=True, eq=False)
class SignalLanes:
    """Surface-street lanes and signal states of a scene.

    :param lane_id: (nl,) int64 ids of the surface-street lanes with ≥ 2 points, map order.
    :param points: (nl, M, 2) float32 xy, padded with zeros.
    :param seg_valid: (nl, M - 1) bool, segments whose start point is real.
    :param signal_lane: (nS,) int64 ids of every lane that has a signal state at some step.
    :param is_stop: (T, nS) bool, red at that step.
    :param stop_point: (T, nS, 2) float32 stop point xy ((0, 0) when absent).
    :param lane_index: (nS,) int64 index into ``lane_id`` of the signal lane (-1: not a
        surface-street lane, never violated).
    """

    lane_id: np.ndarray
    points: np.ndarray
    seg_valid: np.ndarray
    signal_lane: np.ndarray
    is_stop: np.ndarray
    stop_point: np.ndarray
    lane_index: np.ndarray


def signal_lanes(scene: Scene, num_steps: int) -> SignalLanes | None:
    """The lanes and signals the violation check needs; None when it can never fire."""
    lanes = [ln for ln in scene.roadmap.lanes
             if int(ln.type) == int(LaneType.SURFACE_STREET) and len(ln.polyline) >= 2]
    sig = scene.signals
    if not lanes or len(sig.step) == 0:
        return None
    most = max(len(ln.polyline) for ln in lanes)
    pts = np.zeros((len(lanes), most, 2), np.float32)
    real = np.zeros((len(lanes), most), bool)
    for k, ln in enumerate(lanes):
        pts[k, :len(ln.polyline)] = ln.polyline[:, :2]
        real[k, :len(ln.polyline)] = True
    lane_id = np.array([ln.id for ln in lanes], np.int64)
    sl = np.unique(sig.lane).astype(np.int64)
    keep = sig.step < num_steps
    j = np.searchsorted(sl, sig.lane[keep])
    t = sig.step[keep]
    state = np.zeros((num_steps, len(sl)), np.int64)
    stop = np.zeros((num_steps, len(sl), 2), np.float32)
    state[t, j] = sig.state[keep]
    stop[t, j] = sig.stop_point[keep, :2]
    first = {}
    for k, i in enumerate(lane_id.tolist()):
        first.setdefault(i, k)
    lane_index = np.array([first.get(int(i), -1) for i in sl], np.int64)
    return SignalLanes(lane_id, pts, real[:, :-1], sl, np.isin(state, _STOP_STATES), stop,
                       lane_index)


def _nearest_segment(q: np.ndarray, pts: np.ndarray, seg_valid: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(lane, segment) indices nearest to points ``q`` (n, 2) by the official (buggy) measure.

    :param pts: (n or 1, nl, M, 2) padded lane points; ``seg_valid`` (n or 1, nl, M - 1).
    """
    a, b = pts[..., :-1, :], pts[..., 1:, :]
    d = b - a
    p = q[:, None, None, :] - a
    den = (d * d).sum(-1)
    num = (p * d).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(den != 0, num / den, np.float32(0))
    o = p + d * np.clip(t, 0, 1)[..., None]  # sic: '+', as the official tool
    dist = np.where(seg_valid, np.sqrt((o * o).sum(-1)), _FAR).reshape(len(q), -1)
    flat = dist.argmin(1)
    return np.divmod(flat, a.shape[-2])


@numba.njit(cache=True)
def _nearest_lane_of(qx, qy, pts, seg_valid):  # pragma: no cover - numba
    best = np.float32(np.inf)
    lane = 0
    for ln in range(pts.shape[0]):
        for k in range(pts.shape[1] - 1):
            if seg_valid[ln, k]:
                dx, dy = pts[ln, k + 1, 0] - pts[ln, k, 0], pts[ln, k + 1, 1] - pts[ln, k, 1]
                px, py = qx - pts[ln, k, 0], qy - pts[ln, k, 1]
                den = dx * dx + dy * dy
                t = (px * dx + py * dy) / den if den != 0 else np.float32(0.0)
                tc = min(max(t, np.float32(0.0)), np.float32(1.0))
                ox, oy = px + dx * tc, py + dy * tc  # sic: '+', as the official tool
                d = np.sqrt(ox * ox + oy * oy)
            else:
                d = _FAR
            if d != d:  # argmin stops at the first NaN
                return ln
            if d < best:
                best = d
                lane = ln
    return lane


@numba.njit(cache=True)
def _nearest_lane(q, pts, seg_valid):  # pragma: no cover - numba
    """:func:`_nearest_segment`'s lane for every point against all lanes (the same float32
    operations; the first minimum in (lane, segment) order, or the first NaN, as argmin)."""
    out = np.empty(q.shape[0], np.int64)
    for i in range(q.shape[0]):
        out[i] = _nearest_lane_of(q[i, 0], q[i, 1], pts, seg_valid)
    return out


def red_light_violation(x: np.ndarray, y: np.ndarray, valid: np.ndarray,
                        lanes: SignalLanes | None) -> np.ndarray:
    """Per-step violation flags (B, E, T) for object centres ``x, y`` (B, E, T) float32.

    A violation at step t: the object is valid at t, its projection on a red signal lane's stop
    segment went from behind the stop point at t-1 to ahead of it at t, and its nearest lane at
    t is that signal lane.
    """
    out = np.zeros(x.shape, bool)
    if lanes is None:
        return out
    T, nS = lanes.is_stop.shape
    ok = lanes.lane_index >= 0
    if not ok.any():
        return out
    # stop "fence" per (step, signal lane): the segment of its lane nearest to the stop point
    js = np.nonzero(ok)[0]
    k = lanes.lane_index[js]
    q = lanes.stop_point[:, js].reshape(-1, 2)  # (T * nJ, 2)
    kk = np.tile(k, T)
    _, seg = _nearest_segment(q, lanes.points[kk][:, None], lanes.seg_valid[kk][:, None])
    a = lanes.points[kk, seg]
    d = lanes.points[kk, seg + 1] - a
    den = (d * d).sum(-1)
    safe = np.where(den != 0, den, 1)
    stop_t = np.where(den != 0, ((q - a) * d).sum(-1) / safe, 0).reshape(T, len(js))
    a, d = a.reshape(T, len(js), 2), d.reshape(T, len(js), 2)
    den, safe = den.reshape(T, len(js)), safe.reshape(T, len(js))
    obj_t = ((x[..., None] - a[..., 0]) * d[..., 0] + (y[..., None] - a[..., 1]) * d[..., 1])
    obj_t = np.where(den != 0, obj_t / safe, 0)  # (B, E, T, nJ)
    behind, ahead = obj_t < stop_t, obj_t > stop_t
    crossed = np.zeros_like(behind)
    crossed[:, :, 1:] = behind[:, :, :-1] & ahead[:, :, 1:]
    cand = crossed & lanes.is_stop[:, js] & valid[..., None]
    hit = cand.any(-1)
    if not hit.any():
        return out
    # current lane only where a red stop line was crossed
    where = np.nonzero(hit)
    qs = np.stack([x[where], y[where]], -1)
    cur = lanes.lane_id[_nearest_lane(np.ascontiguousarray(qs, np.float32), lanes.points,
                                      lanes.seg_valid)]
    out[where] = (cand[where] & (cur[:, None] == lanes.signal_lane[js][None])).any(-1)
    return out
