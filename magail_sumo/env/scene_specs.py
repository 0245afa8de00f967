"""One :class:`~magail_sumo.env.slot_worker.SceneSpec` per recorded scene of some files, each
with its converted bundle (what ``magail-sumo expert`` and single-scene envs are built from)."""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

from converters import iter_scenes
from converters.scene_files import RecordRef
from converters.sumo.bundle import bundle_folder, complete_bundle
from converters.sumo.scenario import ensure_bundle
from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import NameRegistry, printable

from .slot_worker import SceneSpec


def scene_specs(scene_files: Iterable[str | Path], networks: str | Path,
                convert_missing: bool = True, errors: list[str] | None = None,
                time_budget_s: float | None = 600.0) -> list[SceneSpec]:
    """A :class:`SceneSpec` per scene of ``scene_files`` with its bundle under ``networks``
    (``networks/<name>/``, ``name`` = :func:`magail_sumo.outputs.safe_name` of the scenario
    id), converting the scenes that have none yet (baseline run skipped, ``time_budget_s``
    seconds each at most) into ``networks`` once it is claimed
    (:func:`converters.sumo.scenario.ensure_bundle`). Two scenes whose ids map to one name
    are refused (:class:`~magail_sumo.outputs.OutputError`).

    :param errors: when given, a scene (or file) that cannot be used is appended here as a
        one-line reason and left out, instead of raising :class:`MagailSumoError`.
    """
    networks = Path(networks)
    names = NameRegistry()
    out = []

    def fail(msg: str) -> None:
        if errors is None:
            raise MagailSumoError(msg)
        errors.append(msg)

    for f in scene_files:
        try:
            for index, scene in enumerate(iter_scenes(f)):
                sid = scene.scenario_id
                names.name(sid)  # two ids of one name: refused
                if not convert_missing:
                    folder = complete_bundle(networks, sid)
                    if folder is None:
                        fail(f"{bundle_folder(networks, sid)}: no converted bundle for scene "
                             f"{printable(sid)}")
                        continue
                else:
                    try:
                        folder = ensure_bundle(scene, networks, RecordRef(str(f), index),
                                               time_budget_s, claim=True)
                    except MagailSumoError as exc:
                        fail(f"{f}: {exc}")
                        continue
                out.append(SceneSpec(str(f), str(folder), sid))
        except Exception as exc:  # noqa: BLE001 - an unreadable file
            if errors is None:
                raise
            errors.append(printable(f"{f}: " + (str(exc) if isinstance(exc, MagailSumoError)
                                                 else f"{type(exc).__name__}: {exc}"), 400))
    return out


__all__ = ["scene_specs"]
