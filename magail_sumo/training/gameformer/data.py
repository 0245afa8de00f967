"""GameFormer training samples of recorded scenes, and a seeded streaming dataset of them.

Samples are built by :mod:`magail_sumo.models.gameformer_features` (module doc there: the focal
agent's frame, histories, futures, map elements). Every (scene, c, focal) with ``c`` in
``history_steps − 1, + window_stride, …`` (the 20-s ScenarioNet scenes give many windows, each
9.1-s WOMD scene a few), a focal of a type in ``focal_types`` observed at ``c`` with at least
``min_future_steps`` observed future steps, is a training sample. :class:`StreamingDataset`
serves batches without holding the dataset: epoch ``e`` visits the scenes in an order drawn from
``(seed, e)``, groups of ``cache_scenes`` scenes at a time, each group's samples shuffled; only
the scenes of the group being served (plus one) are held (LRU). Batch ``b`` of epoch ``e`` is a
pure function of ``(seed, e, b)``, so a run resumes exactly from the position ``(e, b)``.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from converters.scene_files import read_record
from magail_sumo.models.gameformer_features import (  # noqa: F401  (re-exported)
    MAP_KINDS, OBJECT_TYPES, Frame, History, MapChunks, build_sample, collate, focal_types,
    log_future, log_history, map_chunks)
from magail_sumo.scene import Scene

if TYPE_CHECKING:
    from .config import GameFormerConfig

#: stream word of the dataset's epoch orders (apart from other seeded streams of a run)
DATA_STREAM = 0x6F


def window_steps(scene: Scene, history_steps: int, stride: int) -> np.ndarray:
    """Current steps of the windows of ``scene``: ``history_steps − 1`` on by ``stride``,
    while a future step is left."""
    return np.arange(history_steps - 1, scene.num_steps - 1, stride)


def scene_samples(scene: Scene, cfg: "GameFormerConfig", stride: int, min_future: int
                  ) -> np.ndarray:
    """(S, 2) (current step, focal row) of the samples of ``scene`` (module doc)."""
    tr = scene.tracks
    types = np.isin(tr.type, focal_types(cfg.focal_types))
    out = []
    f = cfg.model.future_steps
    for c in window_steps(scene, cfg.history_steps, stride):
        fut = tr.valid[:, c + 1:c + f + 1].sum(1)
        rows = np.flatnonzero(types & tr.valid[:, c] & (fut >= min_future))
        out.extend((int(c), int(r)) for r in rows)
    return np.array(out, np.int64).reshape(-1, 2)


@dataclass
class SceneData:
    """A scene with its map elements (what the dataset caches)."""

    scene: Scene
    chunks: MapChunks


def scene_data(scene: Scene, cfg: "GameFormerConfig") -> SceneData:
    return SceneData(scene, map_chunks(scene, cfg.map_points, cfg.map_spacing))


def training_sample(sd: SceneData, c: int, focal: int, cfg: "GameFormerConfig"
                    ) -> dict[str, np.ndarray]:
    """The training sample of ``focal`` at step ``c``: :func:`build_sample` plus ``future``
    (N, T, 2) and ``future_mask`` (N, T)."""
    hist = log_history(sd.scene, c, cfg.history_steps)
    s = build_sample(hist, focal, sd.chunks, cfg.max_agents, cfg.map_elements)
    s["future"], s["future_mask"] = log_future(sd.scene, c, s["rows"], s["frame"],
                                               cfg.model.future_steps)
    return s


class StreamingDataset:
    """Seeded batches of training samples over scene records (module doc).

    :param refs: scene records (:class:`converters.scene_files.RecordRef`).
    :param cfg: the ``gameformer`` config. :param seed: the run seed.
    """

    def __init__(self, refs: list, cfg: "GameFormerConfig", seed: int) -> None:
        self.refs, self.cfg, self.seed = list(refs), cfg, int(seed)
        self._read = read_record
        self.index: list[np.ndarray] = []
        for ref in self.refs:  # one pass, nothing kept but the (c, focal) pairs
            self.index.append(scene_samples(read_record(ref), cfg, cfg.window_stride,
                                            cfg.min_future_steps))
        self.num_samples = int(sum(len(i) for i in self.index))
        if self.num_samples == 0:
            raise ValueError("no training sample in the scenes (no focal agent with "
                             f"{cfg.min_future_steps} future steps)")
        self._cache: OrderedDict[int, SceneData] = OrderedDict()
        self._order: tuple[int, np.ndarray] | None = None

    @property
    def batches_per_epoch(self) -> int:
        return -(-self.num_samples // self.cfg.batch_size)

    def epoch_order(self, epoch: int) -> np.ndarray:
        """(num_samples, 3) (scene, c, focal) in the order epoch ``epoch`` serves them."""
        if self._order is not None and self._order[0] == epoch:
            return self._order[1]
        rng = np.random.default_rng([self.seed, DATA_STREAM, epoch])
        scenes = rng.permutation(len(self.refs))
        g = self.cfg.cache_scenes
        parts = []
        for k in range(0, len(scenes), g):
            group = [np.concatenate([np.full((len(self.index[i]), 1), i), self.index[i]], 1)
                     for i in scenes[k:k + g] if len(self.index[i])]
            if group:
                rows = np.concatenate(group)
                parts.append(rows[rng.permutation(len(rows))])
        order = np.concatenate(parts)
        self._order = (epoch, order)
        return order

    def scene(self, i: int) -> SceneData:
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        sd = scene_data(self._read(self.refs[i]), self.cfg)
        self._cache[i] = sd
        while len(self._cache) > self.cfg.cache_scenes + 1:
            self._cache.popitem(last=False)
        return sd

    def batch(self, position: int) -> dict[str, torch.Tensor]:
        """Batch number ``position`` of the run (epoch ``position // batches_per_epoch``)."""
        epoch, b = divmod(position, self.batches_per_epoch)
        order = self.epoch_order(epoch)
        bs = self.cfg.batch_size
        return collate([training_sample(self.scene(int(i)), int(c), int(f), self.cfg)
                        for i, c, f in order[b * bs:(b + 1) * bs]])
