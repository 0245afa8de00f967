"""Expert demonstrations on disk (see :mod:`magail_sumo.expert.record`) and their sampling."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from magail_sumo.config import to_dict
from magail_sumo.errors import MagailSumoError
from magail_sumo.inputs import InputFileError, read_json, regular_file
from magail_sumo.sensors.observation import ObservationConfig, observation_names as names_of
from magail_sumo.sim.dynamics import relayout

from .record import EXPERT_FORMAT, READABLE_FORMATS, observation_hash


class ExpertDataError(MagailSumoError):
    """An expert directory is missing, empty, or does not match the training config."""


def _flat(value, prefix: str = "") -> dict:
    """A config dict's leaves by dotted path (``lidar.range``)."""
    if not isinstance(value, dict):
        return {prefix: value}
    out: dict = {}
    for k, v in value.items():
        out.update(_flat(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def check_observation(directory: Path, meta: dict, observation: ObservationConfig) -> None:
    """Refuse (:class:`ExpertDataError`, one line naming ``directory`` and the differing
    fields) expert data whose recorded ``observation_hash`` is not that of ``observation``.
    Data recorded before the hash (no ``observation_hash``) passes: its layout is checked by
    name only. Data recorded before a field was added (its recorded ``observation`` lacks it)
    is read with that field's default, so it passes when the training config leaves the new
    field at its default."""
    recorded = meta.get("observation_hash")
    if recorded is None or recorded == observation_hash(observation):
        return
    theirs = _flat(meta.get("observation")) if isinstance(meta.get("observation"), dict) else {}
    ours = _flat(to_dict(observation))
    if theirs:
        theirs = _flat(to_dict(ObservationConfig())) | theirs  # fields added since: defaults
        if theirs == ours:
            return
    diff = [f"observation.{k}: expert {theirs.get(k, '<none>')!r}, training "
            f"{ours.get(k, '<none>')!r}" for k in sorted(set(theirs) | set(ours))
            if theirs and theirs.get(k) != ours.get(k)]
    what = "; ".join(diff[:4]) + (f"; {len(diff) - 4} more" if len(diff) > 4 else "") \
        if diff else "observation_hash differs"
    raise ExpertDataError(f"{directory}: expert data recorded with another observation config "
                          f"than training uses ({what}); re-record it with `magail-sumo expert "
                          f"SCENES... --config <training config> --out {directory}`")


@dataclass(frozen=True)
class SceneSteps:
    """A batch of scene steps for the discriminator.

    :param x: (B, V, 2F) float32 tokens ``concat(s, s')`` (zeros where padded).
    :param mask: (B, V) bool, present tokens.
    :param pos: (B, V, 3) float32 pose of each vehicle at the step of s: x, y (m) and yaw (rad,
        counter-clockwise from +x), scene frame (zeros where padded); None when unknown
        (expert data of format ``magail_sumo.expert/1``).
    """

    x: np.ndarray
    mask: np.ndarray
    pos: np.ndarray | None = None


def pad_groups(features: np.ndarray, starts: np.ndarray, sizes: np.ndarray,
               poses: np.ndarray | None = None) -> SceneSteps:
    """Padded (B, V, F) batch of the row groups ``[starts[b], starts[b] + sizes[b])``, with the
    rows' (N, 3) ``poses`` padded alike when given."""
    b = len(starts)
    v = int(sizes.max()) if b else 0
    x = np.zeros((b, max(v, 1), features.shape[1]), np.float32)
    mask = np.zeros((b, max(v, 1)), bool)
    pos = None if poses is None else np.zeros((b, max(v, 1), 3), np.float32)
    for i, (s, n) in enumerate(zip(starts, sizes)):
        x[i, :n] = features[s:s + n]
        mask[i, :n] = True
        if pos is not None:
            pos[i, :n] = poses[s:s + n]
    return SceneSteps(x, mask, pos)


class ExpertDataset:
    """All expert transitions of a directory, grouped by scene step.

    :param directory: what ``magail-sumo expert`` wrote.
    :param observation_names: the training observation layout; a different stored layout is
        refused with :class:`ExpertDataError` naming the first mismatch.
    :param action_layout: the policy's action layout: the recorded ``accel_steer`` actions
        and the observations' previous-action entries (``prev_accel``, ``prev_steer``) are
        given in it (:func:`~magail_sumo.sim.dynamics.relayout`).
    :param observation: the training observation config: data recorded with another (its
        ``observation_hash``: every field, sensor ranges included) is refused naming the
        differing fields (:func:`check_observation`); data recorded before the hash is checked
        by its layout's names (``observation_names`` defaults to this config's).

    Reads formats ``magail_sumo.expert/2`` (with each vehicle's pose at the step of s:
    :attr:`pos`) and ``/1`` (no poses: :attr:`pos` is None, and :meth:`require_poses` refuses
    it).
    """

    def __init__(self, directory: str | Path, observation_names: Sequence[str] | None = None,
                 observation: ObservationConfig | None = None,
                 action_layout: str = "accel_steer") -> None:
        import pyarrow.parquet as pq

        d = Path(directory)
        meta_path = d / "metadata.json"
        if not d.is_dir():
            raise ExpertDataError(f"{d}: expert directory not found")
        if not meta_path.is_file():
            raise ExpertDataError(f"{d}: not an expert directory (no metadata.json; record one "
                                  "with `magail-sumo expert SCENES... --out DIR`)")
        try:
            meta = read_json(meta_path, expected="expert metadata")
        except InputFileError as exc:
            raise ExpertDataError(f"unreadable: {exc}") from None
        if not isinstance(meta, dict):
            raise ExpertDataError(f"{meta_path}: not a JSON object")
        if meta.get("format") not in READABLE_FORMATS:
            raise ExpertDataError(f"{meta_path}: format {meta.get('format')!r}, expected "
                                  f"{EXPERT_FORMAT!r}")
        self.format = meta["format"]
        if observation is not None and observation_names is None:
            observation_names = names_of(observation)
        names = list(meta.get("observation_names", []))
        if observation_names is not None:
            want = list(observation_names)
            if names != want:
                i = next((k for k, (a, b) in enumerate(zip(names, want)) if a != b),
                         min(len(names), len(want)))
                got_i = names[i] if i < len(names) else "<end>"
                want_i = want[i] if i < len(want) else "<end>"
                raise ExpertDataError(
                    f"{d}: observation layout mismatch: expert data has {len(names)} values, the "
                    f"training config {len(want)}; first difference at index {i}: expert "
                    f"{got_i!r} vs config {want_i!r}")
        if observation is not None:  # the same layout may hold other values (sensor ranges)
            check_observation(d, meta, observation)
        self.directory = d
        self.metadata = meta
        self.observation_names = names
        self.obs_dim = len(names)
        parts = []
        for sc in meta.get("scenes", []):
            path = d / sc["parquet"]
            try:
                regular_file(path, "an expert Parquet file")  # a FIFO would block the reader
                parts.append(pq.read_table(path))
            except InputFileError as exc:
                raise ExpertDataError(str(exc)) from None
            except (OSError, ValueError) as exc:
                raise ExpertDataError(f"{path}: unreadable expert file ({exc})") from None
        rows = sum(p.num_rows for p in parts)
        if rows == 0:
            raise ExpertDataError(f"{d}: expert directory holds no transitions")
        import pyarrow as pa

        table = pa.concat_tables(parts)

        def fixed(col: str, width: int) -> np.ndarray:
            arr = table.column(col).combine_chunks()
            return arr.values.to_numpy(zero_copy_only=False).reshape(-1, width).astype(np.float32)

        scene = table.column("scene_id").to_numpy(zero_copy_only=False)
        self.scene_names, scene_code = np.unique(scene, return_inverse=True)
        step = table.column("step").to_numpy().astype(np.int64)
        order = np.lexsort((table.column("track_id").to_numpy(), step, scene_code))
        self.s = fixed("s", self.obs_dim)[order]
        if self.s.shape[1] != self.obs_dim:
            raise ExpertDataError(f"{d}: stored observations have {self.s.shape[1]} values, "
                                  f"metadata names {self.obs_dim}")
        self.s_next = fixed("s_next", self.obs_dim)[order]
        self.action = relayout(fixed("action", 2)[order], action_layout)
        prev = [names.index(n) for n in ("prev_accel", "prev_steer") if n in names]
        if action_layout != "accel_steer" and len(prev) == 2:
            for arr in (self.s, self.s_next):
                arr[:, prev] = relayout(arr[:, prev], action_layout)
        #: (N,) float32 physical acceleration of each transition (m/s², inverse dynamics)
        self.accel = table.column("accel").to_numpy().astype(np.float32)[order]
        self.done = table.column("done").to_numpy(zero_copy_only=False)[order]
        self.scene = scene_code[order]
        self.step = step[order]
        self.track = table.column("track_id").to_numpy()[order]
        #: (N, 3) float32 x, y (m), yaw (rad) at the step of s, scene frame (None: format /1)
        self.pos: np.ndarray | None = None
        if self.format != "magail_sumo.expert/1":
            missing = [c for c in ("x", "y", "yaw") if c not in table.column_names]
            if missing:
                raise ExpertDataError(f"{d}: {self.format} expert data lacks the column(s) "
                                      f"{', '.join(missing)}")
            self.pos = np.stack([table.column(c).to_numpy().astype(np.float64)
                                 for c in ("x", "y", "yaw")], axis=1)[order].astype(np.float32)
        self.tokens = np.concatenate([self.s, self.s_next], axis=1)
        key = self.scene * (self.step.max() + 1) + self.step
        self.group_start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        self.group_size = np.diff(np.r_[self.group_start, len(key)])

    def __len__(self) -> int:
        return len(self.s)

    def require_poses(self, who: str) -> None:
        """:class:`ExpertDataError` (one line, naming the directory) unless the data holds the
        vehicles' poses, which ``who`` needs."""
        if self.pos is None:
            raise ExpertDataError(
                f"{self.directory}: expert data of format {self.format} has no vehicle poses, "
                f"which {who} needs; re-record it with `magail-sumo expert SCENES... --out "
                f"{self.directory}`")

    @property
    def num_scene_steps(self) -> int:
        return len(self.group_start)

    def sample_scene_steps(self, batch_size: int, rng: np.random.Generator) -> SceneSteps:
        """``batch_size`` scene steps drawn uniformly (with replacement), padded + mask."""
        g = rng.integers(0, self.num_scene_steps, batch_size)
        return pad_groups(self.tokens, self.group_start[g], self.group_size[g], self.pos)

    def sample_pairs(self, batch_size: int, rng: np.random.Generator
                     ) -> tuple[np.ndarray, np.ndarray]:
        """``batch_size`` (s, a) pairs for behavioural cloning: (B, F), (B, 2)."""
        i = rng.integers(0, len(self), batch_size)
        return self.s[i], self.action[i]
