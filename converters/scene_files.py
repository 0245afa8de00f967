"""Open any supported recorded-scene file: format detection and lazy iteration.

Supported: WOMD ``Scenario`` TFRecord files/shards (optionally gzip-compressed), ScenarioNet
scenario pickles, ScenarioNet dataset folders (with ``dataset_summary.pkl``) and GPUDrive /
Nocturne JSON scenes (``*.json``, one scene each: :mod:`converters.gpudrive`).
"""

from __future__ import annotations

import stat
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Iterable, Iterator

from converters.files import open_regular, path_problem
from converters.gpudrive.reader import iter_gpudrive, load_gpudrive
from converters.scenarionet.reader import (SUMMARY_FILE, dataset_files, iter_scenarionet,
                                           load_scenarionet)
from converters.tfrecord import iter_records
from converters.womd.reader import iter_womd, parse_record
from magail_sumo.errors import SceneFormatError
from magail_sumo.outputs import printable
from magail_sumo.scene import Scene
from magail_sumo.sim.sumo_config import SumoConfigError, find_config, is_sumo_config

_PICKLE_MAGIC = (b"\x80\x02", b"\x80\x03", b"\x80\x04", b"\x80\x05")


@dataclass(frozen=True)
class SceneRecord:
    """One record of a scene file: the scene, or the error that kept it from being read."""

    path: Path
    index: int | None
    scene: Scene | None = None
    error: SceneFormatError | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


#: a SUMO scenario given where a recorded scene is expected
CITY_NOT_SCENE = ("a SUMO scenario (city), not a recorded scene: evaluate it with "
                  "`magail-sumo evaluate --city`, train on it by listing it in scenes.files")


def detect_format(path: str | PathLike) -> str:
    """``"womd"``, ``"scenarionet"``, ``"scenarionet-dataset"`` or ``"gpudrive"`` (a ``.json``
    file, or a file starting with ``{``).

    :raises SceneFormatError: missing path, symlink loop, a FIFO / device / socket (refused
        without reading: it could block or never end), or a directory that is not a
        ScenarioNet dataset.
    """
    p = Path(path)
    problem, st = path_problem(p)
    if problem:
        raise SceneFormatError(p, None, problem)
    if stat.S_ISDIR(st.st_mode):  # type: ignore[union-attr]
        if (p / SUMMARY_FILE).exists():
            return "scenarionet-dataset"
        try:
            city = find_config(p)
        except SumoConfigError:
            city = p
        if city is not None:
            raise SceneFormatError(p, None, CITY_NOT_SCENE)
        raise SceneFormatError(p, None, "is a directory, expected a scene file "
                                        "(or a ScenarioNet dataset folder with dataset_summary.pkl)")
    with open_regular(p) as fh:
        head = fh.read(2)
    if p.suffix == ".pkl" or head in _PICKLE_MAGIC:
        return "scenarionet"
    if p.suffix.lower() == ".json" or head[:1] == b"{":
        return "gpudrive"
    if is_sumo_config(p):
        raise SceneFormatError(p, None, CITY_NOT_SCENE)
    return "womd"


def iter_scene_records(path: str | PathLike, keep_synthetic: bool = False
                       ) -> Iterator[SceneRecord]:
    """Every record of one file (or ScenarioNet dataset folder), lazily; never raises on bad data.

    Errors about the file as a whole come back as one record with ``index=None``.
    ``keep_synthetic``: keep a track the source marks as generated, not recorded (ScenarioNet
    ``metadata.selected_adv_id``; dropped by default,
    :func:`~converters.scenarionet.reader.scene_from_scenarionet`).
    """
    p = Path(path)
    try:
        fmt = detect_format(p)
        it = ({"womd": iter_womd, "gpudrive": iter_gpudrive}[fmt](p) if fmt in
              ("womd", "gpudrive") else iter_scenarionet(p, keep_synthetic))
        for index, item in it:
            if isinstance(item, SceneFormatError):
                yield SceneRecord(p, index, error=item)
            else:
                yield SceneRecord(p, index, scene=item)
    except SceneFormatError as exc:
        yield SceneRecord(p, exc.record, error=exc)
    except OSError as exc:
        yield SceneRecord(p, None, error=SceneFormatError(p, None, f"cannot read ({exc.strerror or exc})"))


def iter_scenes(paths: Iterable[str | PathLike] | str | PathLike) -> Iterator[Scene]:
    """All scenes of the given files, lazily; raises the first :class:`SceneFormatError`."""
    if isinstance(paths, (str, PathLike)):
        paths = [paths]
    for path in paths:
        for rec in iter_scene_records(path):
            if rec.error is not None:
                raise rec.error
            yield rec.scene  # type: ignore[misc]


def find_scene(paths: Iterable[str | PathLike] | str | PathLike,
               scenario_id: str | None) -> Scene:
    """The scene ``scenario_id`` of the given files (None: their first scene), read lazily up
    to it; raises the first :class:`SceneFormatError` met before it, or one naming the
    file(s) when no scene has that id."""
    for scene in iter_scenes(paths):
        if scenario_id is None or scene.scenario_id == scenario_id:
            return scene
    where = paths if isinstance(paths, (str, PathLike)) else \
        ", ".join(str(p) for p in paths)  # type: ignore[union-attr]
    what = "no scene" if scenario_id is None else f"scenario {printable(scenario_id)} not found"
    raise SceneFormatError(where, None, what)


def load_scene(path: str | PathLike, index: int = 0) -> Scene:
    """The ``index``-th scene of a file."""
    for i, scene in enumerate(iter_scenes(path)):
        if i == index:
            return scene
    raise SceneFormatError(path, index, "no such record")


@dataclass(frozen=True)
class RecordRef:
    """Where one scene lives: a scene file (TFRecord / ScenarioNet pickle) and its record index
    in it (0 for a pickle). Cheap to list (:func:`list_records`) and to pass between processes;
    :func:`read_record` parses just that record."""

    path: str
    index: int = 0

    def __str__(self) -> str:
        return f"{self.path}#{self.index}" if "tfrecord" in Path(self.path).name else self.path


def list_records(path: str | PathLike) -> list[RecordRef]:
    """The scene records of a file or ScenarioNet dataset folder, without parsing any scene
    (a TFRecord's framing is walked, a dataset's summary read; a pickle is one record). A
    record whose framing is bad is still listed (reading it gives its error); a file that
    cannot be opened raises :class:`SceneFormatError`."""
    p = Path(path)
    fmt = detect_format(p)
    if fmt in ("scenarionet", "gpudrive"):
        return [RecordRef(str(p), 0)]
    if fmt == "scenarionet-dataset":
        return [RecordRef(str(f), 0) for f in dataset_files(p)]
    out = []
    for index, data in iter_records(p):
        out.append(RecordRef(str(p), index))
        if isinstance(data, SceneFormatError) and data.fatal_for_file:
            break
    return out


def read_record(ref: RecordRef) -> Scene:
    """The scene of one record (:class:`SceneFormatError` naming file and record when it
    cannot be read); only that record is parsed."""
    p = Path(ref.path)
    fmt = detect_format(p)
    if fmt == "scenarionet":
        return load_scenarionet(p)
    if fmt == "gpudrive":
        if ref.index != 0:
            raise SceneFormatError(p, ref.index, "no such record (a JSON file holds one scene)")
        return load_gpudrive(p)
    if fmt == "scenarionet-dataset":
        files = dataset_files(p)
        if not 0 <= ref.index < len(files):
            raise SceneFormatError(p, ref.index, "no such record")
        return load_scenarionet(files[ref.index])
    for index, data in iter_records(p):
        if index < ref.index:
            if isinstance(data, SceneFormatError) and data.fatal_for_file:
                raise data
            continue
        if isinstance(data, SceneFormatError):
            raise data
        return parse_record(p, index, data)
    raise SceneFormatError(p, ref.index, "no such record")
