"""Convert every scene of many scene files, in parallel, with a summary CSV.

Bad records and failing conversions (a worker that dies or hangs included) are reported per
scene; the batch goes on. Two scenes whose ids map to the same bundle name
(:class:`magail_sumo.outputs.NameRegistry`) are not both converted: the second is a failed row.
The summary CSV keeps the original scenario ids and is written atomically.

Resumable: a scene whose bundle already exists with status ``ok``, the same converter version
(:func:`.scenario.converter_version`) and the same options (:func:`.scenario.options_key`) is
not converted again but is a ``skipped`` row (its quality read from its ``conversion.json``),
unless ``force``. A scenario id met a second time within one batch is a ``skipped`` row too
(the bundle is the first one's: one folder per id). Memory stays flat over any number of
scenes: records are read lazily, at most ``workers`` scenes are in flight, and rows hold only
the small quality dict.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

from converters.scene_files import SceneRecord, iter_scene_records
from magail_sumo.outputs import NameRegistry, OutputError, atomic_write, inside, printable
from magail_sumo.scene import Scene
from magail_sumo.workers import run_jobs

from .bundle import BundleError, bundle_folder, check_bundle
from .scenario import ConvertOptions, convert_scene, converter_version, options_key
from .quality import failed_bars

SUMMARY_COLUMNS = ("file", "record", "scenario_id", "status", "reason", "on_network_rate",
                   "route_rate", "signal_fidelity", "synthesized_lanes", "netconvert_warnings",
                   "ade", "fde", "collisions", "teleports", "parked_overlaps", "seconds",
                   "bars_met", "bars_failed")


@dataclass
class BatchRow:
    """One line of the summary: a converted scene or an unreadable record."""

    file: str
    record: int | None
    scenario_id: str
    status: str  # ok / skipped / failed / unreadable
    reason: str
    quality: dict
    seconds: float

    def csv_row(self) -> list:
        q = self.quality or {}
        base = q.get("sumo_baseline") or {}
        return [self.file, "" if self.record is None else self.record, self.scenario_id,
                self.status, self.reason, q.get("on_network_rate"), q.get("route_rate"),
                q.get("signal_fidelity"), q.get("synthesized_lanes"), q.get("netconvert_warnings"),
                base.get("ade"), base.get("fde"), base.get("collisions"), base.get("teleports"),
                base.get("parked_overlaps"), round(self.seconds, 3), *self._bars(q)]

    def _bars(self, q: dict) -> list[str]:
        """``bars_met`` (yes / no; empty for a scene that did not convert) and
        ``bars_failed`` (the :data:`~.quality.BARS` it falls below, ``;``-separated)."""
        if self.status not in ("ok", "skipped") or not q:
            return ["", ""]
        failed = failed_bars(q)
        return ["no" if failed else "yes", ";".join(failed)]


def converted_before(out: Path, scenario_id: str, options: ConvertOptions) -> dict | None:
    """The ``conversion.json`` of ``scenario_id``'s bundle in ``out`` when it is a complete
    bundle (:func:`.bundle.check_bundle`) written by this converter version with the same
    options; else None."""
    try:
        rep = check_bundle(bundle_folder(out, scenario_id), scenario_id)
    except (BundleError, OSError, OutputError):
        return None
    if rep.get("scenario_id") != scenario_id or \
            rep.get("converter_version") != converter_version() or \
            rep.get("options_key") != options_key(options):
        return None
    return rep


def _convert(job: tuple[str, int | None, Scene, str, ConvertOptions]) -> BatchRow:
    path, index, scene, out, opts = job
    rep = convert_scene(scene, Path(out), opts, source=(path, index))
    return BatchRow(path, index, rep.scenario_id, rep.status, rep.reason, rep.quality,
                    rep.timings.get("total", 0.0))


def _failed(job: tuple, reason: str, seconds: float = 0.0) -> BatchRow:
    path, index, scene, _, _ = job
    return BatchRow(path, index, scene.scenario_id, "failed", f"{printable(scene.scenario_id)}: {reason}",
                    {}, seconds)


#: seconds a worker gets beyond the conversion's own time budget before it is killed
KILL_GRACE_S = 60.0
#: what every scene's conversion process imports (SUMO and the converter): imported once by
#: the process they are forked from (:func:`magail_sumo.workers.run_jobs`' ``preload``), not
#: once per scene (about 0.75 s each)
WORKER_IMPORTS = ("libsumo", "converters.sumo.batch")


def convert_files(inputs: Iterable[str | Path], out: Path, workers: int = 1,
                  options: ConvertOptions | None = None,
                  timeout_s: float | None = None, force: bool = False) -> Iterator[BatchRow]:
    """Rows for every record of ``inputs``: scenes in input order, an unreadable record or a
    skipped scene as soon as it is met.

    A scene that fails in any way (its conversion fails, raises, its worker process dies or
    hangs) is a ``failed`` row with the reason; the batch goes on. A scene already converted
    with this converter version and options, or whose id was met before in this batch, is a
    ``skipped`` row (see the module doc); ``force`` reconverts the former.

    :param workers: > 1: each scene is converted in a fresh worker process
        (:func:`magail_sumo.workers.run_jobs`), killed after ``timeout_s`` seconds (default:
        the options' ``time_budget_s`` plus :data:`KILL_GRACE_S`; None budget: no limit).
    """
    opts = options or ConvertOptions()
    records: Iterator[SceneRecord] = (r for p in inputs for r in iter_scene_records(p))
    if timeout_s is None and opts.time_budget_s is not None:
        timeout_s = opts.time_budget_s + KILL_GRACE_S

    names = NameRegistry()
    seen: dict[str, str] = {}  # scenario id -> where it was first met (file#record)

    def jobs() -> Iterator[tuple | BatchRow]:
        for rec in records:
            if rec.error is not None:
                yield BatchRow(str(rec.path), rec.index, "", "unreadable",
                               printable(str(rec.error), 1000), {}, 0.0)
                continue
            sid = rec.scene.scenario_id
            try:
                names.name(sid)
            except OutputError as exc:
                yield BatchRow(str(rec.path), rec.index, sid, "failed", str(exc), {}, 0.0)
                continue
            if sid in seen:
                yield BatchRow(str(rec.path), rec.index, sid, "skipped",
                               f"{printable(sid)}: repeated scenario id (first met at "
                               f"{seen[sid]}); one bundle per id", {}, 0.0)
                continue
            seen[sid] = f"{printable(str(rec.path))}#{rec.index}"
            if not force:
                done = converted_before(Path(out), sid, opts)
                if done is not None:
                    yield BatchRow(str(rec.path), rec.index, sid, "skipped",
                                   f"{printable(sid)}: already converted (converter "
                                   f"{done['converter_version']}, same options; --force "
                                   "reconverts)", done.get("quality") or {}, 0.0)
                    continue
            yield (str(rec.path), rec.index, rec.scene, str(out), opts)

    if workers <= 1:
        for job in jobs():
            if isinstance(job, BatchRow):
                yield job
                continue
            try:
                row = _convert(job)
            except Exception as exc:  # noqa: BLE001 - one scene's failure is its row
                row = _failed(job, f"{type(exc).__name__}: {' '.join(str(exc).split())}")
            yield row
        return
    unreadable: list[BatchRow] = []  # (and skipped) reported as soon as met, like in-process

    def scene_jobs() -> Iterator[tuple]:
        for job in jobs():
            if isinstance(job, BatchRow):
                unreadable.append(job)
            else:
                yield job

    for res in run_jobs(_convert, scene_jobs(), workers=workers, timeout_s=timeout_s,
                        ordered=True, preload=WORKER_IMPORTS):
        yield from unreadable
        unreadable.clear()
        yield res.value if res.ok else _failed(res.job, res.reason, res.seconds)
    yield from unreadable


def write_summary(path: Path, rows: list[BatchRow]) -> None:
    """Write the summary CSV (one line per record), atomically, refused
    (:class:`~magail_sumo.outputs.OutputError`) through a link out of its folder."""
    with atomic_write(inside(path.parent, path.name), "w") as fh:
        w = csv.writer(fh)
        w.writerow(SUMMARY_COLUMNS)
        for row in rows:
            w.writerow(row.csv_row())
