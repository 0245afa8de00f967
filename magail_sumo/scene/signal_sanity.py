"""Traffic-light sanity of a recorded scene (``magail-sumo inspect``, ``conversion.json``).

Logged data is not always consistent: WOMD has scenes whose recorded drivers run red lights,
and signal records that are missing for some steps or UNKNOWN. :func:`signal_sanity` reports,
per scene (numpy over all tracks and steps at once):

* ``red_light_runs``: logged red-light running by vehicles and cyclists, with the WOSAC
  traffic-light violation rule of :mod:`magail_sumo.scene.traffic_light` (the
  object's projection on a red (STOP / ARROW_STOP) signal lane's stop segment goes from behind
  the stop point to ahead of it between two valid steps while its nearest lane is that signal
  lane): ``events`` (object-steps), ``vehicles`` (distinct tracks) and the first
  :data:`MAX_LISTED` events as ``{"track_id", "step"}``.
* ``gaps``: steps at which a signalled lane has no record although it has records before and
  after (``steps`` in all, ``lanes`` with any, ``longest`` run in steps).
* ``unknown``: records whose state is UNKNOWN (``steps`` in all, ``lanes`` with any,
  ``longest`` run of consecutive UNKNOWN steps).
* ``lanes``: per signalled lane ``{"lane", "records", "first_step", "last_step", "gap_steps",
  "longest_gap", "unknown_steps", "longest_unknown"}``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from magail_sumo.scene import Scene
from magail_sumo.scene.traffic_light import red_light_violation, signal_lanes
from magail_sumo.scene.types import ObjectType, SignalState

MAX_LISTED = 20  #: red-light events listed by track and step
_ROAD_USERS = (int(ObjectType.VEHICLE), int(ObjectType.CYCLIST))


def longest_run(mask: np.ndarray) -> np.ndarray:
    """(n,) length of the longest run of True down each column of a (T, n) bool array."""
    mask = np.asarray(mask, bool)
    if mask.shape[0] == 0:
        return np.zeros(mask.shape[1:], np.int64)
    count = np.cumsum(mask, axis=0)
    reset = np.maximum.accumulate(np.where(~mask, count, 0), axis=0)
    return (count - reset).max(axis=0)


def red_light_runs(scene: Scene) -> np.ndarray:
    """(N, T) bool: track n (a vehicle or cyclist) ran a red light at step t (see module doc)."""
    tr = scene.tracks
    n, t = tr.valid.shape
    out = np.zeros((n, t), bool)
    rows = np.flatnonzero(np.isin(tr.type, _ROAD_USERS))
    lanes = signal_lanes(scene, t)
    if lanes is None or rows.size == 0:
        return out
    x, y = (v[rows].astype(np.float32)[None] for v in (tr.x, tr.y))
    valid = tr.valid[rows][None]
    both = valid.copy()
    both[..., 1:] &= valid[..., :-1]  # a crossing needs the step before as well
    out[rows] = red_light_violation(x, y, both, lanes)[0]
    return out


def signal_sanity(scene: Scene) -> dict[str, Any]:
    """The traffic-light sanity report of ``scene`` (see the module doc); plain JSON data."""
    sig = scene.signals
    t_n = scene.num_steps
    lanes = np.unique(sig.lane).astype(np.int64)
    state = np.full((t_n, len(lanes)), -1, np.int64)  # -1: no record
    keep = (sig.step >= 0) & (sig.step < t_n)
    state[sig.step[keep], np.searchsorted(lanes, sig.lane[keep])] = sig.state[keep]
    has = state >= 0
    steps = np.arange(t_n)[:, None]
    first = np.where(has.any(0), np.argmax(has, axis=0), t_n)
    last = np.where(has.any(0), t_n - 1 - np.argmax(has[::-1], axis=0), -1)
    gap = ~has & (steps > first) & (steps < last)
    unknown = state == int(SignalState.UNKNOWN)
    runs = red_light_runs(scene)
    ev_row, ev_step = np.nonzero(runs)
    order = np.lexsort((ev_row, ev_step))[:MAX_LISTED]
    gap_n, gap_long = gap.sum(0), longest_run(gap)
    unk_n, unk_long = unknown.sum(0), longest_run(unknown)
    return {
        "signal_lanes": int(len(lanes)),
        "records": int(len(sig)),
        "red_light_runs": {
            "events": int(runs.sum()),
            "vehicles": int(runs.any(1).sum()),
            "listed": [{"track_id": int(scene.tracks.id[ev_row[k]]), "step": int(ev_step[k])}
                       for k in order],
        },
        "gaps": {"steps": int(gap_n.sum()), "lanes": int((gap_n > 0).sum()),
                 "longest": int(gap_long.max(initial=0))},
        "unknown": {"steps": int(unk_n.sum()), "lanes": int((unk_n > 0).sum()),
                    "longest": int(unk_long.max(initial=0))},
        "lanes": [{"lane": int(lanes[j]), "records": int(has[:, j].sum()),
                   "first_step": int(first[j]), "last_step": int(last[j]),
                   "gap_steps": int(gap_n[j]), "longest_gap": int(gap_long[j]),
                   "unknown_steps": int(unk_n[j]), "longest_unknown": int(unk_long[j])}
                  for j in range(len(lanes))],
    }


def checked_signal_sanity(scene: Scene) -> dict[str, Any]:
    """:func:`signal_sanity`, or ``{"error": "<one line>"}`` when it fails on odd data: the
    check must not make a scene that reads and converts fail."""
    try:
        return signal_sanity(scene)
    except Exception as exc:  # noqa: BLE001 - a diagnostic, never fatal
        return {"error": f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:300]}


def format_signal_sanity(report: dict[str, Any]) -> str:
    """One line for ``inspect``'s text output."""
    if "error" in report:
        return f"not checked ({report['error']})"
    if not report["signal_lanes"]:
        return "none (no signal records)"
    red, gaps, unk = report["red_light_runs"], report["gaps"], report["unknown"]
    return (f"{report['signal_lanes']} lanes; red-light runs {red['events']} "
            f"({red['vehicles']} vehicles); gaps {gaps['steps']} steps on {gaps['lanes']} "
            f"lanes (longest {gaps['longest']}); unknown {unk['steps']} steps on "
            f"{unk['lanes']} lanes (longest {unk['longest']})")
