"""The converted-bundle layout, defined once: what :func:`.scenario.convert_scene` writes, how a
complete bundle is recognised, and its reader (:class:`SceneBundle`);
:func:`.scenario.ensure_bundle` converts a scene whose bundle is missing.

A networks folder ``DIR`` holds one bundle folder per scene, ``DIR/<name>/``, where ``<name>``
is :func:`magail_sumo.outputs.safe_name` of the scenario id (:func:`bundle_folder`: the id
itself for every real WOMD id; an id that is not a plain file name gets its safe characters
plus a hash). A bundle folder holds (:class:`BundleLayout`):

* ``<name>.net.xml``: the SUMO network (plus the plain ``.nod/.edg/.con.xml`` it is built from);
* ``<name>.rou.xml``: the routes (vehicle ids = the scene's track ids);
* ``<name>.parking.add.xml``: a parking space for each non-moving vehicle off the lanes
  (:mod:`.parking`), when there are any;
* ``<name>.tll.xml``: the signal programs, when the scene has signals;
* ``<name>.sumocfg``: a configuration ``sumo -c`` opens as is (relative file names);
* ``<name>.xodr``: OpenDRIVE, when asked for;
* ``netconvert-warnings.txt``: netconvert's warnings verbatim, when it gave any (their count is
  ``quality.netconvert_warnings``);
* ``conversion.json`` (:data:`REPORT_FILE`): the conversion report, with the original
  ``scenario_id``, ``status``, ``files`` (every other file of the folder) and ``unconverted``
  (objects not in SUMO, e.g. parked off-network vehicles, pedestrians).

A bundle is *complete* (:func:`check_bundle`) when its report is readable, says ``status`` ok
for this scenario id (a report without an id, from early versions, is taken as this scene's),
and the configuration, network, routes and every file the report lists are there. Bundles are
renamed into place only when written (see :mod:`.scenario`), so a folder is either a whole
bundle (of a successful or a failed conversion) or absent.
"""

from __future__ import annotations

import json
import stat
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from magail_sumo.errors import MagailSumoError
from magail_sumo.inputs import InputFileError, path_problem, read_json
from magail_sumo.outputs import (MARKER, OutputError, claim_output_dir, inside, printable,
                                 read_marker, safe_name, write_text)
from magail_sumo.scene import Scene
from magail_sumo.sim.sumo_config import SumoConfigError, SumoInputs, read_config

#: the conversion report of a bundle folder
REPORT_FILE = "conversion.json"
#: files an unmarked networks folder may hold beside its bundles (see :func:`claim_networks_dir`)
NETWORKS_EXTRAS = ("README.md", "summary.csv")
LOCKS = ".locks"  #: sub-folder of a networks folder with one lock file per bundle being made


class BundleError(MagailSumoError):
    """A scene bundle is missing a file, does not match its scene, or could not be made."""


def bundle_folder(root: str | Path, scenario_id: str) -> Path:
    """``root/<safe name>``: the bundle folder of a scene (see the module doc)."""
    return inside(root, safe_name(scenario_id))


@dataclass(frozen=True)
class BundleLayout:
    """The file paths of one bundle folder (module doc). ``name``: the files' stem."""

    folder: Path
    name: str

    @classmethod
    def of(cls, folder: str | Path, scenario_id: str) -> "BundleLayout":
        """The layout of ``scenario_id``'s bundle in ``folder``."""
        return cls(Path(folder), safe_name(scenario_id))

    def _file(self, suffix: str) -> Path:
        return self.folder / f"{self.name}{suffix}"

    @property
    def net(self) -> Path:
        return self._file(".net.xml")

    @property
    def routes(self) -> Path:
        return self._file(".rou.xml")

    @property
    def signals(self) -> Path:
        """Signal programs (only when the scene has signals)."""
        return self._file(".tll.xml")

    @property
    def parking(self) -> Path:
        """Parking spaces of the parked vehicles off the lanes (only when there are any)."""
        return self._file(".parking.add.xml")

    @property
    def sumocfg(self) -> Path:
        return self._file(".sumocfg")

    @property
    def opendrive(self) -> Path:
        return self._file(".xodr")

    @property
    def warnings(self) -> Path:
        """netconvert's warnings as it printed them (only when it gave any)."""
        return self.folder / "netconvert-warnings.txt"

    @property
    def report(self) -> Path:
        return self.folder / REPORT_FILE

    def required(self) -> tuple[Path, ...]:
        """The files every complete bundle has, in the order they are checked."""
        return self.sumocfg, self.net, self.routes, self.report

    def sumo_inputs(self) -> SumoInputs:
        """What SUMO runs of this bundle are started with: its configuration read
        (:func:`~magail_sumo.sim.sumo_config.read_config`: outputs, logs and ports dropped)
        naming only the bundle's own network, routes and signal programs;
        :class:`BundleError` (one line) otherwise."""
        own = {str(p.resolve()) for p in (self.net, self.routes, self.signals, self.parking)}
        try:
            return read_config(self.sumocfg, allowed=own)
        except SumoConfigError as exc:
            raise BundleError(str(exc)) from None


def is_bundle_dir(path: Path) -> bool:
    """Whether ``path`` is a bundle folder (a real folder with a conversion report; complete
    or not)."""
    return path.is_dir() and not path.is_symlink() and (path / REPORT_FILE).is_file()


def read_report(folder: str | Path) -> dict[str, Any]:
    """The ``conversion.json`` of a bundle folder; :class:`BundleError` when unreadable."""
    path = Path(folder) / REPORT_FILE
    try:  # a regular file of at most 64 MiB, JSON nested at most 64 deep
        report = read_json(path, expected="a conversion report")
    except InputFileError as exc:
        raise BundleError(f"{Path(folder)}: unreadable bundle file: {exc}") from None
    if not isinstance(report, dict):
        raise BundleError(f"{path}: not a conversion report")
    return report


def check_bundle(folder: str | Path, scenario_id: str) -> dict[str, Any]:
    """The conversion report of ``scenario_id``'s complete bundle in ``folder`` (module doc);
    :class:`BundleError` (one line naming the file) when it is not complete."""
    files = BundleLayout.of(folder, scenario_id)
    for path in files.required():
        problem, st = path_problem(path)
        if problem == "no such file":
            raise BundleError(f"{path}: bundle file not found (convert the scene with "
                              "converters.sumo.scenario.convert_scene)")
        if problem or stat.S_ISDIR(st.st_mode):  # type: ignore[union-attr]
            raise BundleError(f"{path}: bundle file {problem or 'is a directory'}")
    report = read_report(files.folder)
    if report.get("scenario_id", scenario_id) != scenario_id:
        raise BundleError(f"{files.report}: bundle of scenario "
                          f"{printable(str(report.get('scenario_id')))}, not "
                          f"{printable(scenario_id)}")
    if report.get("status") != "ok":
        raise BundleError(f"{files.report}: conversion failed: "
                          f"{printable(str(report.get('reason', '')), 1000)}")
    listed = report.get("files")
    for name in listed if isinstance(listed, list) else ():
        if not isinstance(name, str) or Path(name).name != name:
            raise BundleError(f"{files.report}: bad file name {printable(str(name))!r}")
        if not (files.folder / name).is_file():
            raise BundleError(f"{files.folder / name}: bundle file not found")
    return report


def complete_bundle(root: str | Path, scenario_id: str) -> Path | None:
    """``scenario_id``'s bundle folder under the networks folder ``root`` when it is complete
    (:func:`check_bundle`), else None."""
    try:
        folder = bundle_folder(root, scenario_id)
        check_bundle(folder, scenario_id)
    except (BundleError, OutputError, OSError):
        return None
    return folder


@dataclass(frozen=True)
class SceneBundle:
    """A converted scene bundle: the recorded scene plus its complete bundle folder, read.

    :param sumocfg: the SUMO configuration.
    :param sumo_rows: (V,) track rows (into ``scene.tracks``) of the vehicles in the routes.
    :param sumo_ids: SUMO id of each of those vehicles.
    :param unconverted: ``conversion.json``'s list of objects left out of SUMO.
    :param parked: ids of the route vehicles with a stop (the non-moving ones, :mod:`.parking`).
    :param inputs: what SUMO runs of the bundle start with (:meth:`BundleLayout.sumo_inputs`).
    :param spaces: ids of the parked vehicles in a parking space off the lanes (the others stop
        on the lane they block): scenery, not agents of ``SumoDrivingEnv`` unless the scene
        names them (the SDC, a track to predict).
    """

    scene: Scene
    folder: Path
    sumocfg: Path
    sumo_rows: np.ndarray
    sumo_ids: tuple[str, ...]
    unconverted: tuple[dict, ...]
    parked: frozenset[str] = frozenset()
    inputs: SumoInputs | None = None
    spaces: frozenset[str] = frozenset()

    @property
    def files(self) -> BundleLayout:
        """The bundle's file paths (network, signals, ...)."""
        return BundleLayout.of(self.folder, self.scene.scenario_id)

    @classmethod
    def load(cls, scene: Scene, folder: str | Path) -> "SceneBundle":
        """Check (:func:`check_bundle`) and read the bundle folder of ``scene``;
        :class:`BundleError` when it is incomplete or its routes name vehicles that are not
        tracks of ``scene``."""
        files = BundleLayout.of(folder, scene.scenario_id)
        report = check_bundle(files.folder, scene.scenario_id)
        try:
            root = ET.parse(files.routes).getroot()
        except ET.ParseError as exc:
            raise BundleError(f"{files.folder}: unreadable bundle file: "
                              f"{' '.join(str(exc).split())}") from None
        row_of = {int(t): k for k, t in enumerate(scene.tracks.id.tolist())}
        ids = tuple(v.get("id") for v in root.iter("vehicle"))
        bad = [i for i in ids if not i.lstrip("-").isdigit() or int(i) not in row_of]
        if bad:
            raise BundleError(f"{files.routes}: vehicle {printable(str(bad[0]))} is not "
                              f"a track of scene {printable(scene.scenario_id)}")
        rows = np.array([row_of[int(i)] for i in ids], np.int64)
        parked = frozenset(v.get("id") for v in root.iter("vehicle") if v.find("stop") is not None)
        spaces = frozenset(v.get("id") for v in root.iter("vehicle")
                           if v.find("stop") is not None and v.find("stop").get("parkingArea"))
        return cls(scene, files.folder, files.sumocfg, rows, ids,
                   tuple(report.get("unconverted", ())), parked, files.sumo_inputs(), spaces)


def _networks_entry(path: Path) -> bool:
    """What an unmarked networks folder may hold: bundle folders and :data:`NETWORKS_EXTRAS`."""
    if path.is_symlink():
        return False
    if path.is_dir():
        return (path / REPORT_FILE).is_file()
    return path.name in NETWORKS_EXTRAS


def claim_networks_dir(folder: str | Path, owned: list[str] | tuple[str, ...] = ()) -> Path:
    """Make ``folder`` a networks folder of ``convert`` (bundles ``<name>/``), or
    :class:`~magail_sumo.outputs.OutputError` when it is not one.

    It may be new, empty, marked by any magail_sumo command
    (:func:`magail_sumo.outputs.claim_output_dir`), or an unmarked folder that holds converted
    bundles (folders with ``conversion.json``; at least one) and nothing else but ``README.md``
    and ``summary.csv``, as the repository ships ``networks/`` and older versions left their
    output: it is then marked.
    """
    d = Path(folder)
    if d.is_dir() and not d.is_symlink() and read_marker(d) is None:
        entries = [p for p in d.iterdir() if p.name != MARKER]
        bundles = [p for p in entries if p.is_dir() and not p.is_symlink()]
        if bundles and all(_networks_entry(p) for p in entries):
            write_text(inside(d, MARKER), json.dumps({"tools": {}}, indent=1))
    return claim_output_dir(d, "convert", owned)
