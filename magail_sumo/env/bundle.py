"""A converted scene bundle: the recorded scene plus the SUMO scenario folder built from it.

The folder is what :func:`converters.sumo.scenario.convert_scene` writes to ``DIR/<id>/``:
``<id>.sumocfg``, ``<id>.net.xml``, ``<id>.rou.xml`` (vehicle ids = WOMD track ids) and
``conversion.json`` (``unconverted``: objects not in SUMO, e.g. parked off-network vehicles,
pedestrians). ``<id>`` is :func:`magail_sumo.outputs.safe_name` of the scenario id (the id
itself for every real WOMD id); ``conversion.json`` holds the original id, checked on load.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import printable, safe_name
from magail_sumo.scene import Scene


class BundleError(MagailSumoError):
    """A scene bundle is missing a file or does not match its scene."""


@dataclass(frozen=True)
class SceneBundle:
    """Scene plus SUMO files.

    :param sumocfg: the SUMO configuration.
    :param sumo_rows: (V,) track rows (into ``scene.tracks``) of the vehicles in the routes.
    :param sumo_ids: SUMO id of each of those vehicles.
    :param unconverted: ``conversion.json``'s list of objects left out of SUMO.
    :param parked: ids of the route vehicles with a parking stop.
    """

    scene: Scene
    folder: Path
    sumocfg: Path
    sumo_rows: np.ndarray
    sumo_ids: tuple[str, ...]
    unconverted: tuple[dict, ...]
    parked: frozenset[str] = frozenset()

    @classmethod
    def load(cls, scene: Scene, folder: str | Path) -> "SceneBundle":
        """Check and read the bundle folder of ``scene``; :class:`BundleError` when incomplete."""
        folder = Path(folder)
        sid = scene.scenario_id
        name, shown = safe_name(sid), printable(sid)
        files = {key: folder / f"{name}{key}" for key in (".sumocfg", ".net.xml", ".rou.xml")}
        files["conversion.json"] = folder / "conversion.json"
        for path in files.values():
            if not path.is_file():
                raise BundleError(f"{path}: bundle file not found (convert the scene with "
                                  "converters.sumo.scenario.convert_scene)")
        try:
            report = json.loads(files["conversion.json"].read_text())
            root = ET.parse(files[".rou.xml"]).getroot()
        except (ValueError, ET.ParseError) as exc:
            raise BundleError(f"{folder}: unreadable bundle file: {' '.join(str(exc).split())}") \
                from None
        if not isinstance(report, dict):
            raise BundleError(f"{files['conversion.json']}: not a conversion report")
        if report.get("scenario_id", sid) != sid:
            raise BundleError(f"{files['conversion.json']}: bundle of scenario "
                              f"{printable(str(report.get('scenario_id')))}, not {shown}")
        if report.get("status") != "ok":
            raise BundleError(f"{files['conversion.json']}: conversion failed: "
                              f"{printable(str(report.get('reason', '')), 1000)}")
        row_of = {int(t): k for k, t in enumerate(scene.tracks.id.tolist())}
        ids = tuple(v.get("id") for v in root.iter("vehicle"))
        bad = [i for i in ids if not i.lstrip("-").isdigit() or int(i) not in row_of]
        if bad:
            raise BundleError(f"{files['.rou.xml']}: vehicle {printable(str(bad[0]))} is not "
                              f"a track of scene {shown}")
        rows = np.array([row_of[int(i)] for i in ids], np.int64)
        parked = frozenset(v.get("id") for v in root.iter("vehicle") if v.find("stop") is not None)
        return cls(scene, folder, files[".sumocfg"], rows, ids,
                   tuple(report.get("unconverted", ())), parked)
