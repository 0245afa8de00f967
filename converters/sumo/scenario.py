"""Convert one recorded scene into a SUMO scenario folder with ``conversion.json``.

``DIR/<id>/`` receives ``<id>.net.xml`` (plus the plain ``.nod/.edg/.con.xml`` it is built
from), ``<id>.rou.xml``, ``<id>.tll.xml`` (when the scene has signals), ``<id>.sumocfg`` and
``conversion.json``. Simulation step: 0.1 s, SUMO time 0 = the scene's first step.
Recorded driving off the mapped lanes gets synthesised lanes (:mod:`.synthesis`), listed under
``synthesized`` and counted in ``quality.synthesized_lanes``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from magail_sumo.scene import LaneType, Scene

from .matching import build_index
from .network import build_network
from .quality import lane_segments, on_network_rate, route_rate, run_baseline
from .routes import build_routes, write_routes
from .signals import build_programs, write_programs
from .synthesis import carried_states, synthesize_lanes
from .topology import TimeBudgetExceeded, plan_network

STEP_LENGTH = 0.1  #: s


@dataclass
class ConvertOptions:
    """Options of :func:`convert_scene`."""

    cycle_signals: bool = False  #: repeat the recorded signal sequence past the end of the log
    baseline: bool = True  #: run SUMO once for signal_fidelity and sumo_baseline
    #: seconds one scene may take (the bundled scenes need about 1 s); past it the scene fails
    #: with a "time budget ... exceeded" reason. Checked between stages and during the junction
    #: path search; netconvert is killed at it. None: no limit.
    time_budget_s: float | None = 600.0


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

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in ("scenario_id", "status", "reason", "files",
                                              "unconverted", "synthesized", "timings", "quality")}


def write_sumocfg(path: Path, sid: str, additional: list[str], end: float) -> None:
    """A configuration that ``sumo -c`` / ``sumo-gui -c`` open as is (relative file names)."""
    add = f'    <additional-files value="{",".join(additional)}"/>\n' if additional else ""
    path.write_text(
        "<configuration>\n  <input>\n"
        f'    <net-file value="{sid}.net.xml"/>\n    <route-files value="{sid}.rou.xml"/>\n{add}'
        "  </input>\n  <time>\n"
        f'    <begin value="0"/>\n    <end value="{end:.1f}"/>\n'
        f'    <step-length value="{STEP_LENGTH}"/>\n'
        "  </time>\n  <processing>\n"
        '    <collision.action value="warn"/>\n    <time-to-teleport value="30"/>\n'
        "  </processing>\n</configuration>\n")


def convert_scene(scene: Scene, out_root: Path, options: ConvertOptions | None = None) -> ConversionReport:
    """Convert ``scene`` into ``out_root/<scenario_id>/``; never raises on a bad scene.

    A failing stage gives ``status="failed"`` with ``reason`` naming the stage and problem.
    """
    import sumolib

    opts = options or ConvertOptions()
    sid = scene.scenario_id
    out = Path(out_root) / sid
    out.mkdir(parents=True, exist_ok=True)
    rep = ConversionReport(sid)
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
        lap("plan")
        stage = "synthesize"
        lanes = {l.id: l for l in scene.roadmap.lanes
                 if l.id in plan.lane_edges or l.id in plan.junction_lanes}
        index_bike = build_index(lanes)
        index_car = build_index({i: l for i, l in lanes.items() if l.type != LaneType.BIKE_LANE})
        synthesized = synthesize_lanes(scene, plan, index_car, index_bike)
        rep.synthesized = [s.to_dict() for s in synthesized]
        lap("synthesize")
        stage = "netconvert"
        built = build_network(scene, plan, out, timeout_s=remaining())
        lap("netconvert")
        stage = "load network"
        net = sumolib.net.readNet(str(built.net_file), withInternal=True)
        lap("load_network")
        stage = "signals"
        programs = None
        additional: list[str] = []
        if len(scene.signals) and net.getTrafficLights():
            programs = build_programs(scene, plan, net)
            write_programs(out / f"{sid}.tll.xml", programs, STEP_LENGTH, opts.cycle_signals)
            additional.append(f"{sid}.tll.xml")
            rep.unconverted.extend({"kind": "signal", "id": int(lane),
                                    "reason": "signalled lane is not part of a traffic-light link"}
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
        write_routes(out / f"{sid}.rou.xml", routes, STEP_LENGTH, end)
        write_sumocfg(out / f"{sid}.sumocfg", sid, additional, end)
        lap("routes")
        rep.files = sorted(p.name for p in out.iterdir() if p.name != "conversion.json")
        stage = "quality"
        seg = lane_segments(net)
        rep.quality = {
            "on_network_rate": on_network_rate(scene, seg),
            # the same with the states carried by synthesised lanes counted as off the map
            "on_network_rate_map_only": on_network_rate(scene, seg,
                                                        carried_states(scene, synthesized)),
            "synthesized_lanes": len(synthesized),
            "route_rate": route_rate(scene, seg, routes, net),
            "signal_fidelity": None,
            "netconvert_warnings": len(built.warnings),
            "sumo_baseline": None,
        }
        lap("quality")
        if opts.baseline:
            stage = "sumo run"
            base = run_baseline(scene, str(out / f"{sid}.sumocfg"), routes, programs)
            rep.quality["signal_fidelity"] = base.signal_fidelity
            rep.quality["sumo_baseline"] = {"ade": base.ade, "fde": base.fde,
                                            "collisions": base.collisions,
                                            "teleports": base.teleports}
            lap("sumo_run")
        rep.status = "ok"
    except Exception as exc:  # a bad scene must not stop a batch
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        if isinstance(exc, TimeBudgetExceeded):
            msg = f"time budget of {budget:g} s exceeded (ConvertOptions.time_budget_s / --timeout-s)"
        rep.reason = f"{sid}: {stage}: {msg}"
    rep.timings["total"] = round(sum(v for k, v in rep.timings.items() if k != "total"), 4)
    (out / "conversion.json").write_text(json.dumps(rep.to_dict(), indent=1))
    return rep
