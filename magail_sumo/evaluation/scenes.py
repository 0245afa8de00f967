"""Scenes prepared once for an evaluation: each read from its file and checked once, with its
converted SUMO bundle, then handed to every method and rollout (the worker processes get the
parsed scene, not its file to parse again)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from converters.scene_files import iter_scene_records
from converters.sumo.bundle import BundleError, bundle_folder, check_bundle, complete_bundle
from converters.sumo.scenario import ensure_bundle
from magail_sumo.errors import MagailSumoError
from magail_sumo.evaluation.protocol import DEFAULT_TIMEOUT_S, N_STEPS, Problems, log
from magail_sumo.outputs import NameRegistry, OutputError, inside, one_line, printable
from magail_sumo.scene import Scene


@dataclass(frozen=True, eq=False)
class PreparedScene:
    """One scene of an evaluation, prepared once for all its methods and rollouts.

    :param file: the resolved path of the scene's file (the manifest records it).
    :param scene: the parsed scene (with its roadmap).
    :param bundle: its converted SUMO bundle; None while no method needs SUMO.
    """

    file: str
    scene: Scene
    bundle: Path | None = None

    @property
    def scenario_id(self) -> str:
        return self.scene.scenario_id


def read_scenes(scene_files: list[str], error: Problems) -> dict[str, PreparedScene]:
    """The usable scenes of ``scene_files`` by scenario id, in file order; each unreadable
    record, repeated id, scene too short for the protocol or id without a file name is reported
    (``error``) and left out."""
    scenes: dict[str, PreparedScene] = {}
    names = NameRegistry()  # rollouts file names of the scenes
    for f in scene_files:
        try:
            for rec in iter_scene_records(f):
                if rec.error is not None:
                    error(" ".join(str(rec.error).split()))
                    continue
                sc = rec.scene
                shown = printable(sc.scenario_id)
                if sc.scenario_id in scenes:
                    error(f"scenario {shown}: given twice ({f}); first kept")
                    continue
                if sc.num_steps < sc.current_time_index + 1 + N_STEPS:
                    error(f"scenario {shown}: {sc.num_steps} steps, needs "
                          f"{sc.current_time_index + 1 + N_STEPS} (current step + 80)")
                    continue
                try:
                    names.name(sc.scenario_id)
                except OutputError as exc:
                    error(f"{f}: {exc}; scenario {shown} skipped")
                    continue
                scenes[sc.scenario_id] = PreparedScene(str(Path(f).resolve()), sc)
        except MagailSumoError as exc:
            error(" ".join(str(exc).split()))
        except Exception as exc:  # noqa: BLE001 - one file's failure, the batch goes on
            error(f"{f}: {type(exc).__name__}: {one_line(exc)}")
    return scenes


def bundle(scene: Scene, networks: Path | None, out: Path,
           timeout_s: float | None = DEFAULT_TIMEOUT_S) -> Path:
    """A converted bundle of ``scene``: reused from ``networks`` when complete, else converted
    into ``out/networks`` (:func:`converters.sumo.scenario.ensure_bundle`), refused
    (:class:`~magail_sumo.outputs.OutputError`) when that leads out of ``out`` (a symbolic
    link). A bundle of the scene in ``networks`` that cannot be used (incomplete, a FIFO or
    device for a file, an unreadable report) is named in a log line with the reason, not
    passed over in silence."""
    if networks and complete_bundle(networks, scene.scenario_id) is None:
        try:
            folder = bundle_folder(networks, scene.scenario_id)
            if os.path.lexists(folder):
                check_bundle(folder, scene.scenario_id)
        except (BundleError, OutputError, OSError) as exc:
            log(f"{one_line(exc, 300)}: bundle not used; the scene is converted into "
                f"{Path(out) / 'networks'}")
    return ensure_bundle(scene, inside(out, "networks"), time_budget_s=timeout_s,
                         search=[networks] if networks else [], claim=True)


def with_bundles(scenes: dict[str, PreparedScene], networks: Path | None, out: Path,
                 timeout_s: float | None, error: Problems) -> dict[str, PreparedScene]:
    """``scenes`` with their converted bundles (:func:`bundle`); a scene whose conversion fails
    is reported and left out."""
    ready: dict[str, PreparedScene] = {}
    for sid, ps in scenes.items():
        try:
            ready[sid] = PreparedScene(ps.file, ps.scene, bundle(ps.scene, networks, out,
                                                                 timeout_s))
        except MagailSumoError as exc:
            error(" ".join(str(exc).split()))
        except Exception as exc:  # noqa: BLE001 - one scene's failure, the batch goes on
            error(f"scenario {sid}: {type(exc).__name__}: {one_line(exc)}")
    return ready
