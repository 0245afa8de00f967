"""Convert one recorded scene into a SUMO scenario folder with ``conversion.json``.

``DIR/<name>/`` receives the bundle described in :mod:`.bundle` (the layout and its reader are
defined there): ``<name>.net.xml`` (plus the plain ``.nod/.edg/.con.xml`` it is built from),
``<name>.rou.xml``, ``<name>.parking.add.xml`` (when the scene has parked vehicles off the
lanes), ``<name>.tll.xml`` (when the scene has signals), ``<name>.sumocfg`` and
``conversion.json``. Simulation step: 0.1 s, SUMO time 0 = the scene's first step.

``<name>`` is :func:`magail_sumo.outputs.safe_name` of the scenario id: the id itself for every
real WOMD id; an id that is not a plain file name (``/``, ``..``, control characters, empty,
longer than 100 characters) gets its safe characters plus a hash, so nothing is written outside
``DIR``; ``conversion.json`` keeps the original ``scenario_id``. The bundle is built in a
temporary folder beside it and renamed into place, so a crash or a full disk leaves the old
bundle or none, never a half-written one; an existing ``DIR/<name>`` is only replaced when it is
a bundle of the same scene (or empty).
Recorded driving off the mapped lanes gets synthesised lanes (:mod:`.synthesis`), listed under
``synthesized`` and counted in ``quality.synthesized_lanes``.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from magail_sumo.inputs import InputFileError, read_json
from magail_sumo.outputs import OutputError, inside, inside_dir, one_line, printable, safe_name
from magail_sumo.scene import LaneType, Scene
from magail_sumo.scene.driving_side import driving_side
from magail_sumo.scene.signal_sanity import checked_signal_sanity
from magail_sumo.scene.types import STEP_LENGTH

from .baseline import UNMAPPED, run_baseline
from .bundle import (LOCKS, REPORT_FILE, BundleError, BundleLayout, bundle_folder,
                     complete_bundle)
from .bundle import claim_networks_dir  # re-exported: callers import it from here
from .junction_shapes import fill_junction_shapes
from .matching import build_index
from .network import build_network
from .parking import write_parking
from .pedestrians import check_built, plan_pedestrians
from .lanes import lane_segments
from .quality import on_network, route_quality
from .routes import build_routes, write_routes
from .signals import build_programs, unmapped_reason, write_programs
from .synthesis import carried_states, synthesize_lanes
from .topology import TimeBudgetExceeded, plan_network
from .opendrive import write_opendrive

if TYPE_CHECKING:
    from converters.scene_files import RecordRef


#: Version of the converter's outputs, recorded in ``conversion.json`` (``converter_version``,
#: with a digest of this package's sources appended: see :func:`converter_version`). ``convert``
#: skips a scene whose bundle has the same version and options; bump it when outputs change.
CONVERTER_VERSION = "2"
#: vehicles behind a low route rate listed in ``conversion.json`` (``quality.route_misses``)
MISSES_KEPT = 50


@dataclass
class ConvertOptions:
    """Options of :func:`convert_scene`."""

    cycle_signals: bool = False  #: repeat the recorded signal sequence past the end of the log
    baseline: bool = True  #: run SUMO once for signal_fidelity and sumo_baseline
    #: seconds one scene may take (the bundled scenes need about 1 s); past it the scene fails
    #: with a "time budget ... exceeded" reason. Checked between stages and during the junction
    #: path search; netconvert is killed at it. None: no limit.
    time_budget_s: float | None = 600.0
    #: also write ``<id>.xodr`` (OpenDRIVE, :mod:`converters.sumo.opendrive`)
    opendrive: bool = False
    #: sidewalks on road edges and crossings from the crosswalks (:mod:`.pedestrians`), so
    #: recorded pedestrians walk in SUMO as persons and SUMO's drivers yield to them
    #: (:class:`magail_sumo.sim.session.Obstacles`); ``conversion.json``'s ``pedestrians``
    #: says how many crosswalks became crossings and why the others were dropped
    pedestrians: bool = False


def converter_version() -> str:
    """``CONVERTER_VERSION`` plus a digest of the ``converters/sumo`` sources, so that a changed
    converter never reuses a bundle written by another one."""
    global _VERSION
    if _VERSION is None:
        import hashlib

        h = hashlib.sha256()
        for f in sorted(Path(__file__).parent.glob("*.py")):
            h.update(f.name.encode() + b"\0" + f.read_bytes() + b"\0")
        _VERSION = f"{CONVERTER_VERSION}+{h.hexdigest()[:12]}"
    return _VERSION


_VERSION: str | None = None


def options_key(options: ConvertOptions) -> str:
    """Digest of the options that affect a bundle's files (all but ``time_budget_s``;
    ``pedestrians`` only when set, so the default key is the one written before it existed)."""
    import dataclasses
    import hashlib

    d = {k: v for k, v in dataclasses.asdict(options).items() if k != "time_budget_s"
         and not (k == "pedestrians" and not v)}
    return hashlib.sha256(json.dumps(d, sort_keys=True, default=repr).encode()).hexdigest()[:16]


@dataclass
class ConversionReport:
    """The content of ``conversion.json``."""

    scenario_id: str
    status: str = "failed"
    reason: str = ""
    files: list[str] = field(default_factory=list)
    unconverted: list[dict] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    quality: dict[str, Any] = field(default_factory=dict)
    synthesized: list[dict] = field(default_factory=list)  #: lanes made from off-map driving
    #: checks of the recorded data itself: what the reader repaired or inferred
    #: (``Scene.data_quality``: ``dropped_references``, ``inferred_connectivity``, ``notes``)
    #: and ``signals`` (traffic-light sanity,
    #: :func:`magail_sumo.scene.signal_sanity.signal_sanity`)
    data_quality: dict[str, Any] = field(default_factory=dict)
    converter_version: str = ""  #: :func:`converter_version` of the converter that wrote it
    options_key: str = ""  #: :func:`options_key` of the options it was written with
    #: where the scene was read from, when the caller knows: ``{"file": path, "record": index}``
    #: (a folder of bundles is a training scene pool through it, see
    #: :mod:`magail_sumo.env.scene_pool`)
    source: dict[str, Any] = field(default_factory=dict)
    #: with ``ConvertOptions.pedestrians``: sidewalks, crosswalks, crossings built, the planned
    #: crossings and the crosswalks dropped with their reason
    #: (:meth:`.pedestrians.PedestrianPlan.to_dict`); absent otherwise
    pedestrians: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        keys = ("scenario_id", "status", "reason", "files", "unconverted", "synthesized",
                "timings", "quality", "data_quality", "converter_version", "options_key",
                "source") + (("pedestrians",) if self.pedestrians is not None else ())
        return {k: getattr(self, k) for k in keys}


def _check_replaceable(folder: Path, sid: str) -> None:
    """:class:`OutputError` unless ``folder`` is absent, empty or a bundle of scene ``sid``."""
    if not folder.exists() and not folder.is_symlink():
        return
    if folder.is_symlink() or not folder.is_dir():
        raise OutputError(f"{folder}: exists and is not a bundle folder; not replaced")
    if not any(folder.iterdir()):
        return
    conv = folder / REPORT_FILE
    if not conv.is_file():
        raise OutputError(f"{folder}: holds files that are not a converted bundle; not replaced")
    try:
        other = read_json(conv, expected="a conversion report").get("scenario_id", sid)
    except (InputFileError, AttributeError):
        return  # a damaged report of ours: replace the bundle
    if other != sid:
        raise OutputError(f"{folder}: holds the bundle of scenario {printable(str(other))!r}, "
                          f"not {printable(sid)!r} (file name collision); not replaced")


def _move_into_place(tmp: Path, folder: Path, sid: str) -> None:
    """Rename the finished bundle ``tmp`` to ``folder`` (replacing an old bundle of ``sid``)."""
    _check_replaceable(folder, sid)
    if not folder.exists():
        os.rename(tmp, folder)
        return
    trash = Path(tempfile.mkdtemp(prefix=f".{folder.name[:60]}.", suffix=".old",
                                  dir=folder.parent))
    os.rename(folder, trash / "bundle")
    os.rename(tmp, folder)
    shutil.rmtree(trash, ignore_errors=True)


def _disk_full(folder: Path) -> bool:
    """Less than 1 MiB left where ``folder`` lies (a failed stage is then a full disk's doing)."""
    try:
        return shutil.disk_usage(folder).free < 2 ** 20
    except OSError:
        return False


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _one_line(exc: BaseException) -> str:
    return one_line(exc) or type(exc).__name__


def write_sumocfg(path: Path, sid: str, additional: list[str], end: float) -> None:
    """A configuration that ``sumo -c`` / ``sumo-gui -c`` open as is (relative file names).

    :param sid: the file name stem of the bundle's files (the safe name of the scenario id)."""
    files = BundleLayout(path.parent, sid)
    add = f'    <additional-files value="{",".join(additional)}"/>\n' if additional else ""
    path.write_text(
        "<configuration>\n  <input>\n"
        f'    <net-file value="{files.net.name}"/>\n'
        f'    <route-files value="{files.routes.name}"/>\n{add}'
        "  </input>\n  <time>\n"
        f'    <begin value="0"/>\n    <end value="{end:.1f}"/>\n'
        f'    <step-length value="{STEP_LENGTH}"/>\n'
        "  </time>\n  <processing>\n"
        '    <collision.action value="warn"/>\n    <time-to-teleport value="30"/>\n'
        "  </processing>\n</configuration>\n")


def convert_scene(scene: Scene, out_root: Path, options: ConvertOptions | None = None,
                  source: tuple[str, int | None] | None = None) -> ConversionReport:
    """Convert ``scene`` into ``out_root/<safe name>/`` (see the module doc); never raises on
    a bad scene.

    A failing stage gives ``status="failed"`` with ``reason`` naming the stage and problem (the
    id printed through :func:`~magail_sumo.outputs.printable`). A failed write (a full disk, a
    folder in the way that is not this scene's bundle) also gives ``status="failed"`` and leaves
    ``out_root`` as it was. ``source`` (file, record index) is recorded in
    ``conversion.json``.
    """
    import sumolib

    opts = options or ConvertOptions()
    sid = scene.scenario_id
    name = safe_name(sid)  # file names; sid stays the id in conversion.json and messages
    rep = ConversionReport(sid, data_quality=scene.data_quality.to_dict(),
                           converter_version=converter_version(),
                           options_key=options_key(opts),
                           source={} if source is None else
                           {"file": str(source[0]), "record": source[1]})
    try:
        final = bundle_folder(out_root, sid)
        _check_replaceable(final, sid)
        Path(out_root).mkdir(parents=True, exist_ok=True)
        out = Path(tempfile.mkdtemp(prefix=f".{name[:60]}.", suffix=".tmp", dir=out_root))
        os.chmod(out, 0o777 & ~_umask())  # mkdtemp makes it private; a bundle is not
    except (OSError, OutputError) as exc:
        rep.reason = f"{printable(sid)}: output: {_one_line(exc)}"
        rep.timings["total"] = 0.0
        return rep
    files = BundleLayout(out, name)  # the bundle's files, written in the temporary folder
    io_error: OSError | None = None
    stage = "network plan"
    clock = time.perf_counter()

    budget = opts.time_budget_s
    deadline = None if budget is None else time.monotonic() + budget

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        rep.timings[name] = round(now - clock, 4)
        clock = now
        if deadline is not None and time.monotonic() > deadline:
            raise TimeBudgetExceeded("time budget exceeded")

    def remaining() -> float | None:
        return None if deadline is None else max(1.0, deadline - time.monotonic())

    try:
        plan = plan_network(scene, deadline)
        rep.unconverted.extend(plan.unconverted)
        if plan.linked:  # a repair of the recorded map: reported with the reader's
            added = sum(len(x) for _, x in plan.linked.values())
            rep.data_quality["inferred_connectivity"]["successors"] += added
            rep.data_quality["notes"] = [*rep.data_quality["notes"], (
                f"{added} successor links inferred for lanes recorded without any entry or "
                "exit lane (their ends meet other lanes')")]
        lap("plan")
        stage = "synthesize"
        lanes = {l.id: l for l in scene.roadmap.lanes
                 if l.id in plan.lane_edges or l.id in plan.junction_lanes}
        index_bike = build_index(lanes)
        index_car = build_index({i: l for i, l in lanes.items() if l.type != LaneType.BIKE_LANE})
        synthesized = synthesize_lanes(scene, plan, index_car, index_bike)
        rep.synthesized = [s.to_dict() for s in synthesized]
        lap("synthesize")
        peds = None
        if opts.pedestrians:
            stage = "pedestrians"
            peds = plan_pedestrians(scene, plan)
            lap("pedestrians")
        stage = "netconvert"
        side = driving_side(scene.roadmap)  # left: SUMO's left-hand network
        rep.data_quality["driving_side"] = side.to_dict()
        built = build_network(scene, plan, out, name, timeout_s=remaining(), pedestrians=peds,
                              lefthand=side.side == "left")
        if built.warnings:
            files.warnings.write_text("\n".join(built.warnings) + "\n")
        if peds is not None:
            check_built(peds, built.net_file, built.warnings)
            rep.pedestrians = peds.to_dict()
        lap("netconvert")
        stage = "junction shapes"
        filled = fill_junction_shapes(built.net_file)
        lap("junction_shapes")
        stage = "load network"
        net = sumolib.net.readNet(str(built.net_file), withInternal=True)
        lap("load_network")
        stage = "signals"
        programs = None
        additional: list[str] = []
        if len(scene.signals) and net.getTrafficLights():
            programs = build_programs(scene, plan, net)
            write_programs(files.signals, programs, STEP_LENGTH, opts.cycle_signals)
            additional.append(files.signals.name)
            rep.unconverted.extend({"kind": "signal", "id": int(lane),
                                    "reason": unmapped_reason(scene, plan, int(lane))}
                                   for lane in programs.unmapped_lanes)
        elif len(scene.signals):
            rep.unconverted.extend({"kind": "signal", "id": int(lane),
                                    "reason": "no traffic-light junction was built"}
                                   for lane in scene.signals.lanes.tolist())
        lap("signals")
        stage = "routes"
        routes, unconverted = build_routes(scene, plan, index_car, index_bike, net)
        rep.unconverted.extend(unconverted)
        end = scene.num_steps * STEP_LENGTH
        write_routes(files.routes, routes, STEP_LENGTH, end)
        spaces = [(r.id, r.spot, r.length, r.width) for r in routes
                  if r.spot is not None and not r.spot.blocking]
        if spaces:
            write_parking(files.parking, spaces)
            additional.insert(0, files.parking.name)
        write_sumocfg(files.sumocfg, name, additional, end)
        lap("routes")
        if opts.opendrive:
            stage = "opendrive"
            write_opendrive(built.net_file, files.opendrive, timeout_s=remaining())
            lap("opendrive")
        rep.files = sorted(p.name for p in out.iterdir() if p.name != REPORT_FILE)
        stage = "quality"
        seg = lane_segments(net)
        on, on_map, off = on_network(scene, seg, carried_states(scene, synthesized))
        rate, misses = route_quality(scene, seg, routes, net, off, rep.unconverted)
        rep.quality = {
            "on_network_rate": on,
            # the same with the states carried by synthesised lanes counted as off the map
            "on_network_rate_map_only": on_map,
            # the vehicles behind an on-network rate below 1 (at most MISSES_KEPT)
            "off_network": off[:MISSES_KEPT],
            "synthesized_lanes": len(synthesized),
            "route_rate": rate,
            # the vehicles behind a route rate below 1 (at most MISSES_KEPT, with why)
            "route_misses": misses[:MISSES_KEPT],
            "signal_fidelity": None,
            "netconvert_warnings": len(built.warnings),
            # junctions whose polygon now reaches every lane end (:mod:`.junction_shapes`)
            "junction_shapes_filled": filled,
            "sumo_baseline": None,
        }

        rep.data_quality["signals"] = checked_signal_sanity(scene)
        lap("quality")
        if opts.baseline:
            stage = "sumo run"
            base = run_baseline(scene, str(files.sumocfg), routes, programs)
            rep.quality["signal_fidelity"] = base.signal_fidelity
            # the signalled lanes behind a signal fidelity below 1, worst first
            rep.quality["signal_misses"] = [
                {**m, "reason": unmapped_reason(scene, plan, m["lane"])}
                if m["reason"] == UNMAPPED else m for m in base.signal_misses]
            rep.quality["sumo_baseline"] = {"ade": base.ade, "fde": base.fde,
                                            "collisions": base.collisions,
                                            "teleports": base.teleports,
                                            "parked_overlaps": base.parked_overlaps}
            lap("sumo_run")
        rep.status = "ok"
    except Exception as exc:  # a bad scene must not stop a batch
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if isinstance(exc, TimeBudgetExceeded):
            msg = f"time budget of {budget:g} s exceeded (ConvertOptions.time_budget_s / --timeout-s)"
        elif isinstance(exc, OSError):  # a full disk: the file being written, in one line
            where = exc.filename if exc.filename is not None else out
            msg = f"{where}: cannot write ({exc.strerror or type(exc).__name__})"
        rep.reason = f"{printable(sid)}: {stage}: {printable(msg, 1000)}"
        if isinstance(exc, OSError):  # writing failed (a full disk): nothing is moved into place
            io_error = exc
        elif _disk_full(out):  # netconvert exits 0 with a truncated net on a full disk
            io_error = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            rep.reason += f" ({io_error.strerror})"
    except BaseException:  # interrupted: leave no temporary folder behind
        shutil.rmtree(out, ignore_errors=True)
        raise
    rep.timings["total"] = round(sum(v for k, v in rep.timings.items() if k != "total"), 4)
    try:
        if io_error is not None:
            raise io_error
        # the folder is renamed into place only when complete: a plain write is atomic enough
        files.report.write_text(json.dumps(rep.to_dict(), indent=1))
        _move_into_place(out, final, sid)
    except (OSError, OutputError) as exc:
        shutil.rmtree(out, ignore_errors=True)
        if rep.status == "ok":
            rep.status = "failed"
            rep.reason = f"{printable(sid)}: write: {_one_line(exc)}"
    return rep


def ensure_bundle(scene: Scene, networks: str | Path, source: RecordRef | None = None,
                  time_budget_s: float | None = 600.0, *, search: Sequence[str | Path] = (),
                  claim: bool = False) -> Path:
    """A complete bundle folder of ``scene``: the first found in ``search`` then ``networks``
    (:func:`~.bundle.complete_bundle`), else the scene converted once into ``networks`` (SUMO baseline
    run skipped, ``time_budget_s`` at most) and its new folder returned.

    Safe across processes: a lock file per bundle (``networks/.locks/<name>``) lets one
    converter at a time in; the others then find the bundle.

    :param source: the scene's :class:`~converters.scene_files.RecordRef`, recorded in
        ``conversion.json`` (a folder of bundles is then a training scene pool).
    :param claim: claim ``networks`` (:func:`~.bundle.claim_networks_dir`) before converting into it.
    :raises BundleError: the conversion failed (one line with its reason).
    """
    sid = scene.scenario_id
    for root in (*search, networks):
        if (found := complete_bundle(root, sid)) is not None:
            return found
    if claim:
        claim_networks_dir(networks)
    networks = Path(networks)
    name = safe_name(sid)
    locks = inside_dir(networks, LOCKS)
    with open(inside(locks, name), "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            if (found := complete_bundle(networks, sid)) is not None:
                return found  # converted by another process meanwhile
            rep = convert_scene(scene, networks, ConvertOptions(
                baseline=False, time_budget_s=time_budget_s),
                source=None if source is None else (source.path, source.index))
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
    if rep.status != "ok":
        raise BundleError(f"scenario {printable(sid)}: conversion failed: {rep.reason}")
    return bundle_folder(networks, sid)
