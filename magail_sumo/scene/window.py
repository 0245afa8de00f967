"""Evaluation windows: a fixed-length piece of a longer recorded scene, as a scene of its own.

WOSAC scores 91-step scenes: steps ``0..10`` are the history (``current_time_index`` 10), then
80 simulated steps (8 s at 0.1 s). Many real scenes are longer (about 20 s in the ScenarioNet
pickles) and start at ``current_time_index`` 0 with no tracks to predict, so scoring them as they
are sees one history step and only the SDC. :func:`window` cuts log steps
``[start, start + length)`` out of such a scene: step ``start + k`` of the source is step ``k`` of
the window, and the window's current step is ``current``.

Everything time-indexed is sliced: every track array (N × T → N' × length), the timestamps
(shifted to start at 0 s: ``t'_k = t_{start+k} - t_start``) and the signal records (steps
``start..start+length-1``, renumbered from 0). Tracks with no valid state inside the window are
left out (the SDC must be valid at the window's current step, so it is kept); the map, the source ids of the kept tracks and the reader's
data-quality record are carried over unchanged. Units and frames are the source's (metres,
radians CCW from +x, m/s, seconds; the recording's frame).

Tracks to predict (the agents WOSAC scores besides the SDC): those of the source that are kept
and valid at the window's current step; when none are left, :func:`choose_tracks_to_predict`
picks them by a fixed rule.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from magail_sumo.errors import MagailSumoError

from .scene import RequiredPrediction, Scene
from .signals import SignalStates
from .tracks import STATE_FIELDS, Tracks
from .types import ObjectType

#: steps of a WOSAC scene: 11 history steps (current step included) + 80 simulated
WINDOW_STEPS = 91
#: the window's current step (WOMD's ``current_time_index``)
WINDOW_CURRENT = 10
#: most tracks to predict :func:`choose_tracks_to_predict` picks (WOMD's limit)
MAX_TRACKS_TO_PREDICT = 8
#: m, least straight-line distance a chosen track moves from its position at the current step
MIN_MOVE_M = 2.0


class WindowError(MagailSumoError):
    """A window that does not fit its scene (one line naming the scenario and the problem)."""


def window_id(scenario_id: str, start: int) -> str:
    """Scenario id of a window: ``<source id>-w<start>``."""
    return f"{scenario_id}-w{start}"


def choose_tracks_to_predict(scene: Scene, max_tracks: int = MAX_TRACKS_TO_PREDICT,
                             min_move: float = MIN_MOVE_M) -> tuple[RequiredPrediction, ...]:
    """Tracks to predict of a scene that has none, by a fixed rule.

    Candidates are vehicles (:attr:`ObjectType.VEHICLE`) other than the SDC that are valid at
    the current step ``c`` and at every step after it, and that move: the largest distance
    from their position at ``c``, ``max_{t >= c} ||p_t - p_c||`` (x, y; metres), is at least
    ``min_move`` (parked cars, whose recorded positions jitter by centimetres, are left out).
    Of those, the ``max_tracks`` nearest to the SDC at ``c`` (box centres; ties by track
    order) are chosen, nearest first, with difficulty NONE; without an SDC, the first
    ``max_tracks`` in track order.
    """
    tr = scene.tracks
    c = scene.current_time_index
    sdc = scene.sdc_track_index
    cand = (tr.type == ObjectType.VEHICLE) & tr.valid[:, c:].all(axis=1)
    if sdc >= 0:
        cand[sdc] = False
    dx = tr.x[:, c:] - tr.x[:, c:c + 1]
    dy = tr.y[:, c:] - tr.y[:, c:c + 1]
    cand &= np.hypot(dx, dy).max(axis=1, initial=0.0) >= min_move
    idx = np.flatnonzero(cand)
    if sdc >= 0:
        dist = np.hypot(tr.x[idx, c] - tr.x[sdc, c], tr.y[idx, c] - tr.y[sdc, c])
        idx = idx[np.lexsort((idx, dist))]  # by distance, then track order (stable)
    return tuple(RequiredPrediction(int(i)) for i in idx[:max(0, max_tracks)])


def window(scene: Scene, start: int, length: int = WINDOW_STEPS,
           current: int = WINDOW_CURRENT) -> Scene:
    """Steps ``[start, start + length)`` of ``scene`` as a scene with current step ``current``
    and id ``<id>-w<start>`` (see the module doc for what is sliced, kept and chosen).

    :raises WindowError: a window outside the scene (``start < 0``, ``start + length`` past
        its last step, ``current`` not in ``0..length-1``) or one whose SDC is not valid at
        the window's current step (WOSAC scores the SDC from there).
    """
    sid = scene.scenario_id
    n_steps = scene.num_steps
    if length < 1 or not 0 <= current < length:
        raise WindowError(f"scenario {sid}: window length {length} with current step "
                          f"{current} (needs 0 <= current < length)")
    if start < 0 or start + length > n_steps:
        raise WindowError(f"scenario {sid}: window start {start} + length {length} does not "
                          f"fit its {n_steps} steps (start must be in 0..{n_steps - length})")
    tr = scene.tracks
    steps = slice(start, start + length)
    sdc = scene.sdc_track_index
    if sdc >= 0 and not tr.valid[sdc, start + current]:
        raise WindowError(f"scenario {sid}: window start {start}: the SDC (track "
                          f"{int(tr.id[sdc])}) is not valid at its current step (source step "
                          f"{start + current})")
    keep = tr.valid[:, steps].any(axis=1)  # the SDC is: valid at the current step
    new_index = np.cumsum(keep) - 1  # source track index -> window track index
    tracks = Tracks(id=tr.id[keep], type=tr.type[keep],
                    valid=tr.valid[keep, steps],
                    **{f: getattr(tr, f)[keep, steps] for f in STATE_FIELDS})
    sig = scene.signals
    lo, hi = np.searchsorted(sig.step, [start, start + length])  # records are ordered by step
    signals = SignalStates(sig.step[lo:hi] - start, sig.lane[lo:hi], sig.state[lo:hi],
                           sig.stop_point[lo:hi])
    kept_ids = set(tr.id[keep].tolist())
    source_ids = dataclasses.replace(
        scene.source_ids, tracks=tuple(p for p in scene.source_ids.tracks if p[0] in kept_ids))
    ts = scene.timestamps
    out = Scene(
        scenario_id=window_id(sid, start),
        timestamps=ts[steps] - ts[start],
        tracks=tracks,
        roadmap=scene.roadmap,
        signals=signals,
        sdc_track_index=int(new_index[sdc]) if sdc >= 0 else -1,
        current_time_index=current,
        objects_of_interest=tuple(i for i in scene.objects_of_interest if i in kept_ids),
        source_ids=source_ids,
        data_quality=scene.data_quality,
    )
    valid_now = tracks.valid[:, current]
    ttp = tuple(RequiredPrediction(int(new_index[r.track_index]), r.difficulty)
                for r in scene.tracks_to_predict
                if keep[r.track_index] and valid_now[new_index[r.track_index]])
    return dataclasses.replace(out, tracks_to_predict=ttp or choose_tracks_to_predict(out))
