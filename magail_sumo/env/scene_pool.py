"""Training scene pools: any number of recorded scenes, shared out over a fixed set of workers.

A pool is listed once, cheaply, in the trainer (:func:`resolve_pool`: no scene is parsed) from
``scenes.files`` entries, each of which may be

* a scene file: a WOMD TFRecord file or shard (every record), a ScenarioNet pickle;
* a glob (``data/scenarionet/*.pkl``, ``shards/training.tfrecord-*``), expanded in sorted order;
* a ScenarioNet dataset folder (``dataset_summary.pkl``: every scenario it maps);
* a folder of converted bundles (``networks/<name>/conversion.json``): every bundle whose
  ``conversion.json`` records the scene file it came from (``source``);
* a plain SUMO scenario (a city: its ``.sumocfg``, or a folder holding one ``.sumocfg``, e.g.
  ``data/sumo/ingolstadt21``), played by :class:`~magail_sumo.env.city_env.SumoCityEnv` with
  at most ``max_agents`` policy-driven vehicles alive at once and SUMO's drivers for the rest;
* any other folder: the scene files in it (``*.pkl``, ``*.tfrecord*``, ``*.json``; sorted, not recursive).

Entries that match nothing or cannot be listed are *skipped* with a one-line reason (the run
goes on with the rest); an empty pool is an error.

Sharding (:func:`shard_pool`): worker ``w`` of ``W`` owns records ``w, w + W, w + 2W, …``. Each
worker (:class:`PoolCursor`) plays its records in a seeded order: episode ``e`` of worker seed
``s`` plays record ``order[e mod n]`` of the permutation drawn from
``SeedSequence([s, e div n, POOL_STREAM])`` for each pass ``e div n`` over its ``n`` records (a
worker of one record always plays it). A record that cannot be read or converted is skipped —
the next one of the order plays instead — and reported once; which records fail is a property
of the data, so the order stays a pure function of (seed, episode), and exact resume holds.
With more workers than records (``workers.count`` above the pool's size, e.g. one city scenario
on every core), worker ``w`` plays record ``w mod n`` alone: replicas of a record run side by
side, each with its own worker seed, so each plays its own start windows (a recorded scene) or
its own episodes of the demand (a city: SUMO seed, which vehicles the policy drives).

Bundles are converted on demand, the first time a worker plays a scene, into ``networks/`` and
reused from then on (:func:`converters.sumo.scenario.ensure_bundle`; a lock file per bundle keeps
two workers from converting one scene at once). A worker keeps only its most recent scenes' envs
(``cache`` of them), so memory does not grow with the pool.

Slots: a city scenario needs ``max_agents`` slots; a worker holding one recorded scene sizes
its slots exactly (the scene's most concurrent agents,
:func:`max_concurrent_agents`); a worker holding several sizes them to
the largest :func:`agent_bound` of the first :data:`SCAN_RECORDS` records of its order (the
scenes it plays first), computed from each scene alone when the worker starts (no conversion
needed): the vehicles and cyclists alive at once that the controlled setting can pick. The
rest of a large shard is read only when the worker resets into it (a pool of 100,000 files
starts as fast as one of 64); a scene that turns out to need more slots than the worker has is
skipped then, with that reason (``env.controlled: K`` caps the agents of every scene).
"""

from __future__ import annotations

import glob
import os
from collections import OrderedDict
from functools import lru_cache
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from converters.scene_files import RecordRef, list_records, read_record
from converters.sumo.bundle import REPORT_FILE, BundleError, read_report
from converters.sumo.scenario import ensure_bundle
from magail_sumo.errors import MagailSumoError
from magail_sumo.inputs import MiB, InputFileError, read_text
from magail_sumo.outputs import OutputError, one_line, printable
from magail_sumo.scene import ObjectType
from magail_sumo.sim.sumo_config import find_config, is_sumo_config

from .config import SCENE_CACHE, EnvConfig
from .city_env import CityEnvConfig, SumoCityEnv

#: SeedSequence stream of the per-pass scene order (apart from the start-window stream)
POOL_STREAM = 0x5CE4E
_SCENE_SUFFIXES = (".pkl", ".json")
_GLOB_CHARS = set("*?[")
#: records a worker reads at start-up to size its slots (module doc)
SCAN_RECORDS = 64
#: the largest ``skipped_scenes.tsv`` read back (a line per skipped record)
SKIPPED_LIMIT = 256 * MiB


def max_concurrent_agents(env) -> int:
    """Upper bound of the number of agents of ``env`` alive at one step (>= 1), over every
    episode window its config allows (``start_window: random``: over the whole log; with
    ``end_of_life: false`` an agent counts to its window's end; never more than K with
    ``controlled: K``)."""
    tr = env.scene.tracks
    row_of = {int(t): k for k, t in enumerate(tr.id.tolist())}
    rows = np.array([row_of[int(a)] for a in env.possible_agents], np.int64)
    return most_alive(tr.valid[rows], env.config)


def most_alive(valid: np.ndarray, cfg: EnvConfig) -> int:
    """:func:`max_concurrent_agents` of tracks recorded at (A, T) ``valid`` steps (>= 1)."""
    if valid.shape[0] == 0:
        return 1
    t_steps = valid.shape[1]
    if cfg.start_window == "random":  # every window lies in the log; tracks join no earlier
        start, end = 0, t_steps - 1
    else:
        start = min(cfg.start_step, t_steps - 1)
        end = t_steps - 1 if cfg.max_steps is None else min(t_steps - 1, start + cfg.max_steps)
    steps = np.arange(t_steps)
    join = np.where(valid & (steps[None] >= start), steps[None], t_steps).min(axis=1)
    last = t_steps - 1 - np.argmax(valid[:, ::-1], axis=1)
    alive = (steps[None] >= join[:, None]) & (steps[None] <= last[:, None]) & \
        (steps[None] <= end)
    if not cfg.end_of_life and cfg.start_window == "random":
        # an agent drives on past its log's end to its window's end: at step u every track
        # recorded at some step of [u - max_steps, u] may be alive (a window started there)
        span = t_steps if cfg.max_steps is None else cfg.max_steps
        seen = np.concatenate([np.zeros((valid.shape[0], 1), np.int64),
                               np.cumsum(valid, axis=1)], axis=1)
        since = np.maximum(steps - span, 0)
        alive |= (seen[:, steps + 1] - seen[:, since]) > 0
    elif not cfg.end_of_life:  # one window: alive from its join to the window's end
        alive |= (steps[None] >= join[:, None]) & (steps[None] <= end)
    most = int(alive.sum(axis=0).max())
    if not isinstance(cfg.controlled, str):
        most = min(most, int(cfg.controlled))
    return max(1, most)



class ScenePoolError(MagailSumoError):
    """A scene pool has no usable scene."""


@dataclass(frozen=True)
class PoolSkip:
    """A pool entry or record left out, and why (one line)."""

    what: str
    reason: str

    def line(self) -> str:
        return f"{self.what}\t{self.reason}"


def _is_scene_file(p: Path) -> bool:
    return p.is_file() and (p.suffix in _SCENE_SUFFIXES or "tfrecord" in p.name)


def _bundle_sources(folder: Path, skipped: list[PoolSkip]) -> list[RecordRef]:
    refs = []
    for conv in sorted(folder.glob(f"*/{REPORT_FILE}")):
        try:
            rep = read_report(conv.parent)
            src = rep.get("source") or {}
            if rep.get("status") != "ok":
                raise ValueError(f"conversion failed: {rep.get('reason', '')}")
            if not isinstance(src, dict) or not isinstance(src.get("file"), str):
                raise ValueError("no source scene file recorded (converted before sources were "
                                 "recorded: convert it again, or list its scene file)")
            record = src.get("record") or 0
            if type(record) is not int or record < 0:
                raise ValueError(f"bad source record {record!r}")
            path = Path(src["file"])
            if not path.is_absolute() and not path.exists():
                path = folder / path  # relative to the bundles' folder
            if not path.exists():
                raise ValueError(f"source scene file {src['file']} not found")
            refs.append(RecordRef(str(path), record))
        except (OSError, ValueError, AttributeError, BundleError) as exc:
            skipped.append(PoolSkip(str(conv.parent), printable(one_line(exc), 300)))
    return refs


def resolve_pool(entries: Iterable[str], skipped: list[PoolSkip] | None = None
                 ) -> list[RecordRef]:
    """The records of the pool ``entries`` name (module doc), in entry order; what cannot be
    used is appended to ``skipped`` (raised as :class:`ScenePoolError` when None)."""
    out: list[RecordRef] = []
    local: list[PoolSkip] = []
    for entry in entries:
        entry = str(entry)
        if _GLOB_CHARS & set(entry) and not Path(entry).exists():
            paths = [Path(p) for p in sorted(glob.glob(entry))]
            if not paths:
                local.append(PoolSkip(entry, "the pattern matches no file"))
        else:
            paths = [Path(entry)]
        for p in paths:
            try:
                if p.is_file() and is_sumo_config(p):  # a plain SUMO (city) scenario
                    out.append(RecordRef(str(p)))
                    continue
                if p.is_dir() and not (p / REPORT_FILE).exists() \
                        and not (p / "dataset_summary.pkl").exists() \
                        and (cfg := find_config(p)) is not None:
                    out.append(RecordRef(str(cfg)))  # a city scenario folder
                    continue
                if p.is_dir() and not (p / "dataset_summary.pkl").exists():
                    if any(p.glob(f"*/{REPORT_FILE}")):
                        out.extend(_bundle_sources(p, local))
                        continue
                    files = sorted(f for f in p.iterdir() if _is_scene_file(f))
                    if not files:
                        local.append(PoolSkip(str(p), "folder holds no scene file, ScenarioNet "
                                                      "dataset or converted bundle"))
                    for f in files:
                        out.extend(list_records(f))
                    continue
                out.extend(list_records(p))
            except (MagailSumoError, OSError) as exc:
                local.append(PoolSkip(str(p), printable(one_line(exc), 300)))
    if skipped is None and local:
        raise ScenePoolError(f"{local[0].what}: {local[0].reason}")
    if skipped is not None:
        skipped.extend(local)
    return out


def shard_pool(refs: Sequence[RecordRef], workers: int) -> list[tuple[RecordRef, ...]]:
    """Worker ``w``'s records: ``refs[w::workers]``, or with more workers than records the
    one record ``refs[w mod n]`` (replicas, module doc); no empty shard."""
    if not refs:
        return []
    workers = max(1, workers)
    if workers > len(refs):
        return [(refs[w % len(refs)],) for w in range(workers)]
    return [tuple(refs[w::workers]) for w in range(workers)]


def agent_bound(scene, config: EnvConfig) -> int:
    """Upper bound (>= 1) of the agents of ``scene`` alive at one step under ``config``,
    from the scene alone: the vehicles and cyclists (the only objects SUMO routes) between their
    first and last valid step at one step, restricted to the SDC / tracks to predict for those ``controlled`` settings and capped
    at K for ``controlled: K``."""
    tr = scene.tracks
    rows = np.isin(tr.type, [ObjectType.VEHICLE, ObjectType.CYCLIST])
    c = config.controlled
    if isinstance(c, str) and c != "all":
        want = np.zeros(len(tr.id), bool)
        if c in ("sdc", "scored"):
            want[scene.sdc_track_index] = True
        if c in ("tracks_to_predict", "scored"):
            want[[p.track_index for p in scene.tracks_to_predict]] = True
        rows &= want
    valid = tr.valid[rows]
    if not valid.any():
        return 1
    t_steps = valid.shape[1]
    has = valid.any(axis=1)
    first = np.argmax(valid, axis=1)[has]
    last = (t_steps - 1 - np.argmax(valid[:, ::-1], axis=1))[has]
    steps = np.arange(t_steps)  # a track holds its slot from its first to its last valid step
    most = int(((steps[None] >= first[:, None]) & (steps[None] <= last[:, None])).sum(0).max())
    if not isinstance(c, str):
        most = min(most, int(c))
    return max(1, most)


def is_city(ref: RecordRef) -> bool:
    """Whether ``ref`` is a plain SUMO (city) scenario rather than a recorded scene (its file
    a SUMO configuration, :func:`~magail_sumo.sim.sumo_config.is_sumo_config`; cached)."""
    return _is_config(ref.path)


@lru_cache(maxsize=4096)
def _is_config(path: str) -> bool:
    return is_sumo_config(path)


def city_slots(city, ref: RecordRef) -> int:
    """Slots of a city scenario: its config's ``max_agents`` (required)."""
    cap = None if city is None else city.max_agents
    if cap is None:
        raise ScenePoolError(f"{ref.path}: a city scenario needs a cap on its agents "
                             "(city.max_agents) to size its training slots")
    return int(cap)


def start_problem(scene, config: EnvConfig) -> str | None:
    """Why no episode of ``config`` can start in ``scene`` (None: it can): the earliest start
    (``start_step``, or ``min_history`` with random windows) must leave a step to take."""
    key = "min_history" if config.start_window == "random" else "start_step"
    first = getattr(config, key)
    if first > scene.num_steps - 2:
        return (f"{first} leaves no step to take in scene {printable(scene.scenario_id)!r} "
                f"({scene.num_steps} steps)")
    return None


def playable_scene(ref: RecordRef, config: EnvConfig):
    """The scene of record ``ref``, read; :class:`MagailSumoError` when no episode of
    ``config`` can start in it (:func:`start_problem`); the reader's errors otherwise."""
    scene = read_record(ref)
    if (problem := start_problem(scene, config)) is not None:
        raise MagailSumoError(f"env start: {problem}")
    return scene


class EnvCache:
    """The ``size`` most recently used envs of a worker by key (a record, a group of records):
    :meth:`get` marks one used, :meth:`put` closes the least recently used beyond ``size``,
    :meth:`close` closes them all."""

    def __init__(self, size: int) -> None:
        self.size = max(1, size)
        self._envs: OrderedDict = OrderedDict()

    def get(self, key):
        """The env kept under ``key`` (now the most recently used), or None."""
        env = self._envs.get(key)
        if env is not None:
            self._envs.move_to_end(key)
        return env

    def put(self, key, env) -> None:
        self._envs[key] = env
        while len(self._envs) > self.size:
            _, old = self._envs.popitem(last=False)
            old.close()

    def close(self) -> None:
        for env in self._envs.values():
            env.close()
        self._envs.clear()


class PoolCursor:
    """A worker's view of its shard: which record each episode plays (module doc), the env of
    each (built on demand, ``cache`` most recent kept) and the records that failed.

    :param refs: the worker's records. :param networks: the bundles folder.
    :param seed: the worker's seed. :param make_env: ``(scene, bundle folder) -> env``.
    :param config: the env config (a scene too short for its episode start is skipped).
    :param city: :class:`~magail_sumo.env.city_env.CityEnvConfig` of the city scenarios.
    :param convert_budget_s: time budget of one on-demand conversion.
    """

    def __init__(self, refs: Sequence[RecordRef], networks: str | Path, seed: int,
                 make_env: Callable, config: EnvConfig, cache: int = SCENE_CACHE,
                 convert_budget_s: float | None = 600.0, city=None) -> None:
        if not refs:
            raise ScenePoolError("a worker needs at least one scene")
        self.refs = tuple(refs)
        self.networks = Path(networks)
        self.seed = seed
        self.make_env = make_env
        self.config = config
        self.city = city
        self.cache = max(1, cache)
        self.convert_budget_s = convert_budget_s
        #: the worker's slot count when sized from :func:`agent_bound` (several records): a
        #: scene whose bound is larger is skipped when played; None: no such check
        self.slots: int | None = None
        self.failed: dict[int, str] = {}  #: record position -> reason (skipped from then on)
        self.new_failures: list[PoolSkip] = []  #: failures not yet reported to the trainer
        self._envs = EnvCache(self.cache)

    def order(self, epoch: int) -> np.ndarray:
        n = len(self.refs)
        if n == 1:
            return np.zeros(1, np.int64)
        rng = np.random.default_rng(np.random.SeedSequence(
            [self.seed % (1 << 64), epoch, POOL_STREAM]))
        return rng.permutation(n)

    def _fail(self, k: int, exc: BaseException) -> None:
        reason = printable(one_line(exc), 300)
        path = self.refs[k].path
        if reason.startswith(path + ": "):  # the file is named in the skip line already
            reason = reason[len(path) + 2:]
        self.failed[k] = reason
        self.new_failures.append(PoolSkip(str(self.refs[k]), reason))

    def env(self, k: int):
        """The env of record ``k`` (built, and its bundle converted, on first use); raises."""
        if (env := self._envs.get(k)) is not None:
            return env
        ref = self.refs[k]
        if is_city(ref):
            env = SumoCityEnv(ref.path, self.city or CityEnvConfig())
        else:
            scene = playable_scene(ref, self.config)
            if self.slots is not None and (need := agent_bound(scene, self.config)) > self.slots:
                raise MagailSumoError(
                    f"env start: up to {need} agents alive at once, more than the worker's "
                    f"{self.slots} slots (sized from the first {SCAN_RECORDS} scenes it plays; "
                    "env.controlled: K caps the agents of every scene)")
            bundle = ensure_bundle(scene, self.networks, ref, self.convert_budget_s)
            env = self.make_env(scene, bundle)
        self._envs.put(k, env)
        return env

    def env_for(self, episode: int):
        """``(record position, env)`` of episode ``episode``: the order's record, or the next
        usable one after records that fail (reported in :attr:`new_failures`)."""
        n = len(self.refs)
        order = self.order(episode // n)
        for j in range(n):
            k = int(order[(episode % n + j) % n])
            if k in self.failed:
                continue
            try:
                return k, self.env(k)
            except MagailSumoError as exc:
                self._fail(k, exc)
            except (OSError, ValueError) as exc:
                self._fail(k, exc)
        raise self.all_failed()

    def all_failed(self) -> ScenePoolError:
        """The error of a worker none of whose scenes could be used (the first failure)."""
        first = min(self.failed)
        return ScenePoolError(f"every scene of this worker failed; first: {self.refs[first]}: "
                              f"{self.failed[first]}")

    def scan(self) -> int:
        """The worker's slot count: exact for one record, else (:attr:`slots`) the largest
        :func:`agent_bound` of the first :data:`SCAN_RECORDS` records of its order (those that
        cannot be read are failed here; the others are read when played, module doc)."""
        if len(self.refs) == 1 and not is_city(self.refs[0]):
            _, env = self.env_for(0)
            return max_concurrent_agents(env)  # exact: no bound to check against
        most = 0
        seen: dict[RecordRef, int | BaseException] = {}  # a pool may repeat a record
        first = self.order(0)[:SCAN_RECORDS].tolist()
        for k in sorted(first):
            ref = self.refs[k]
            if ref not in seen and is_city(ref):
                seen[ref] = city_slots(self.city, ref)
            if ref not in seen:
                try:
                    seen[ref] = agent_bound(playable_scene(ref, self.config), self.config)
                except (MagailSumoError, OSError, ValueError) as exc:
                    seen[ref] = exc
            got = seen[ref]
            if isinstance(got, BaseException):
                self._fail(k, got)
            else:
                most = max(most, got)
        if len(self.failed) == len(self.refs):
            raise ScenePoolError(f"every scene of this worker failed; first: "
                                 f"{self.refs[0]}: {self.failed[0]}")
        if len(self.failed) == len(first) and len(first) < len(self.refs):
            # every scanned record failed: size from the next readable ones, in order
            for k in self.order(0)[SCAN_RECORDS:].tolist():
                try:
                    scene = read_record(self.refs[k])
                    if start_problem(scene, self.config) is None:
                        most = agent_bound(scene, self.config)
                        break
                except (MagailSumoError, OSError, ValueError) as exc:
                    self._fail(k, exc)
            else:
                raise self.all_failed()
        self.slots = max(1, most)
        return self.slots

    def close(self) -> None:
        self._envs.close()


def write_skipped(path: str | Path, skips: Iterable[PoolSkip]) -> None:
    """Append ``skips`` to the run's ``skipped_scenes`` file (tab-separated: scene, reason;
    a line already there is not repeated, e.g. after a resume). The file is opened without
    following a link (``O_NOFOLLOW``: a link swapped in after the caller's
    :func:`~magail_sumo.outputs.inside` check is refused, not written through)."""
    new = not os.path.lexists(path)
    try:
        have = set() if new else set(read_text(path, SKIPPED_LIMIT).splitlines())
    except InputFileError as exc:
        raise OutputError(f"cannot append to {exc}") from None
    skips = [s for s in skips if s.line().replace("\n", " ") not in have]
    if not skips:
        return
    flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(path, flags, 0o666)
    except OSError as exc:
        raise OutputError(f"{path}: cannot append ({exc.strerror or exc})") from None
    with os.fdopen(fd, "a", encoding="utf-8") as fh:
        if new:
            fh.write("scene\treason\n")
        for s in skips:
            fh.write(s.line().replace("\n", " ") + "\n")
        fh.flush()
        os.fsync(fh.fileno())
