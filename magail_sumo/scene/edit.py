"""Taking tracks out of a scene, with every reference to them kept consistent.

:func:`drop_tracks` removes track rows (e.g. a synthetic track that is not human driving) and
remaps what points at tracks: ``sdc_track_index`` (-1 when the SDC is dropped),
``tracks_to_predict`` (entries of dropped tracks removed, the others renumbered),
``objects_of_interest`` (ids of dropped tracks removed) and ``source_ids.tracks``; the reason is
appended to ``data_quality.notes``.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from .scene import RequiredPrediction, Scene
from .tracks import Tracks


def drop_tracks(scene: Scene, rows: Sequence[int], reason: str) -> Scene:
    """``scene`` without the track rows ``rows`` (module doc); the scene itself when ``rows``
    is empty. ``reason`` is a note like ``"track 2192 dropped: synthetic"``."""
    drop = sorted({int(r) for r in rows})
    if not drop:
        return scene
    tr = scene.tracks
    if drop[0] < 0 or drop[-1] >= tr.num_tracks:
        raise IndexError(f"track rows {drop} out of range 0..{tr.num_tracks - 1}")
    keep = np.setdiff1d(np.arange(tr.num_tracks), drop)
    new_index = np.full(tr.num_tracks, -1, np.int64)
    new_index[keep] = np.arange(keep.size)
    tracks = Tracks(**{f.name: getattr(tr, f.name)[keep] for f in dataclasses.fields(Tracks)})
    gone = set(tr.id[drop].tolist())
    sdc = int(new_index[scene.sdc_track_index]) if scene.sdc_track_index >= 0 else -1
    predict = tuple(RequiredPrediction(int(new_index[p.track_index]), p.difficulty)
                    for p in scene.tracks_to_predict if new_index[p.track_index] >= 0)
    names = tuple(pair for pair in scene.source_ids.tracks if pair[0] not in gone)
    dq = scene.data_quality
    return dataclasses.replace(
        scene, tracks=tracks, sdc_track_index=sdc, tracks_to_predict=predict,
        objects_of_interest=tuple(i for i in scene.objects_of_interest if i not in gone),
        source_ids=dataclasses.replace(scene.source_ids, tracks=names),
        data_quality=dataclasses.replace(dq, notes=(*dq.notes, reason)))
