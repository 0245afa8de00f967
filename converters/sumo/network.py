"""Write a :class:`NetworkPlan` as plain XML (.nod/.edg/.con) and build ``<id>.net.xml``.

Log coordinates are kept (``--offset.disable-normalization``). Junction types: signalled
lanes make ``traffic_light`` nodes, stop-sign lanes make ``allway_stop`` nodes when every
incoming edge has a stop sign and ``priority_stop`` otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from magail_sumo.outputs import inside, safe_name
from magail_sumo.scene import Scene

from .bundle import BundleLayout
from .geometry import fmt_shape
from .pedestrians import (NETCONVERT_WALKING, OBSTACLE_CLASS, SIDEWALK, PedestrianPlan,
                          crossing_xml)
from .tools import run_tool
from .topology import NetworkPlan

NETCONVERT_OPTIONS = [
    "--offset.disable-normalization", "true", "--no-turnarounds", "true",
    "--junctions.corner-detail", "0",
    "--junctions.limit-turn-speed", "5.5",
    "--tls.default-type", "static", "--geometry.remove", "false",
    "--walkingareas", "false", "--crossings.guess", "false", "--sidewalks.guess", "false",
    "--edges.join", "false", "--junctions.join", "false", "--no-internal-links", "false",
    "--check-lane-foes.all", "true",
]


@dataclass
class BuiltNetwork:
    """Result of :func:`build_network`: the net file, node types and netconvert warnings."""

    net_file: Path
    plain_files: list[Path]
    node_types: dict[str, str]
    warnings: list[str]


def node_types(scene: Scene, plan: NetworkPlan) -> dict[str, str]:
    """SUMO junction type per node: traffic_light / allway_stop / priority_stop / priority."""
    types = {n: "priority" for n in plan.nodes}
    for lane in scene.signals.lanes.tolist():
        if lane in plan.node_of_lane:
            types[plan.node_of_lane[lane]] = "traffic_light"
    # A stop sign controls the approach to the junction at its position: of the edges that carry
    # (or lead through connections into) its lanes, the one ending at the nearest real junction
    # (a node joining more than one edge in or out) is stopped, not the pieces of the lane that
    # end mid-way where a neighbour starts or ends.
    edge_by_id = {e.id: e for e in plan.edges}
    degree: dict[str, int] = {}
    for e in plan.edges:
        degree[e.from_node] = degree.get(e.from_node, 0) + 1
        degree[e.to_node] = degree.get(e.to_node, 0) + 1
    stopped_edges: set[str] = set()
    for sign in scene.roadmap.stop_signs:
        lanes = set(sign.lanes)
        cands = {e.id for e in plan.edges if lanes & set(e.lanes)}
        cands |= {c.from_edge for c in plan.connections if lanes & set(c.via)}
        cands = sorted(c for c in cands if edge_by_id[c].to_node not in plan.split_nodes)
        junctions = [c for c in cands if degree[edge_by_id[c].to_node] > 2]
        if junctions or cands:
            pos = np.asarray(sign.position[:2], float)
            stopped_edges.add(min(junctions or cands, key=lambda c: float(
                np.hypot(*(np.asarray(plan.nodes[edge_by_id[c].to_node][:2]) - pos)))))
    incoming: dict[str, set[str]] = {}
    for e in plan.edges:
        incoming.setdefault(e.to_node, set()).add(e.id)
    for n, inc in incoming.items():
        hit = inc & stopped_edges
        if hit and types[n] != "traffic_light":
            types[n] = "allway_stop" if hit == inc else "priority_stop"
    return types


def write_plain(plan: NetworkPlan, types: dict[str, str], prefix: Path,
                crossings: str = "", walking: bool = False) -> list[Path]:
    """Write ``prefix``.nod.xml/.edg.xml/.con.xml; returns their paths.

    Sidewalk lanes (:data:`.pedestrians.SIDEWALK`) allow pedestrians only; ``crossings`` (lines
    of ``<crossing>`` elements, :func:`.pedestrians.crossing_xml`) go into the connection file.
    With ``walking`` (a pedestrian network) bike lanes also allow :data:`.pedestrians.OBSTACLE_CLASS`,
    the class of the obstacles SUMO's drivers see, which walking lanes do not allow."""
    bike = f"bicycle {OBSTACLE_CLASS}" if walking else "bicycle"
    nod, edg, con = (Path(f"{prefix}.{k}.xml") for k in ("nod", "edg", "con"))
    with open(nod, "w") as fh:
        fh.write('<nodes>\n')
        for n, (x, y) in plan.nodes.items():
            fh.write(f'  <node id="{n}" x="{x:.2f}" y="{y:.2f}" type="{types.get(n, "priority")}"/>\n')
        fh.write('</nodes>\n')
    with open(edg, "w") as fh:
        fh.write('<edges>\n')
        for e in plan.edges:
            allow = f'allow="{bike}"' if e.bike_only else 'disallow="pedestrian"'
            centre = e.shapes[len(e.shapes) // 2]
            fh.write(f'  <edge id="{e.id}" from="{e.from_node}" to="{e.to_node}" '
                     f'numLanes="{len(e.lanes)}" speed="{e.speed:.2f}" {allow} '
                     f'spreadType="center" shape="{fmt_shape(centre)}">\n')
            for k, (shape, w) in enumerate(zip(e.shapes, e.widths)):
                if e.lanes[k] == SIDEWALK:
                    fh.write(f'    <lane index="{k}" width="{w:.2f}" allow="pedestrian" '
                             f'shape="{fmt_shape(shape)}"/>\n')
                    continue
                param = ("womd_lane", e.lanes[k]) if e.synthesized_for is None else \
                    ("synthesized_for_track", e.synthesized_for)
                fh.write(f'    <lane index="{k}" width="{w:.2f}" shape="{fmt_shape(shape)}">'
                         f'<param key="{param[0]}" value="{param[1]}"/></lane>\n')
            fh.write('  </edge>\n')
        fh.write('</edges>\n')
    with open(con, "w") as fh:
        fh.write('<connections>\n')
        for c in plan.connections:
            shape = f' shape="{fmt_shape(c.shape)}"' if c.shape is not None else ""
            fh.write(f'  <connection from="{c.from_edge}" to="{c.to_edge}" '
                     f'fromLane="{c.from_lane}" toLane="{c.to_lane}"{shape}/>\n')
        fh.write(crossings)
        fh.write('</connections>\n')
    return [nod, edg, con]


def build_network(scene: Scene, plan: NetworkPlan, out_dir: Path, name: str | None = None,
                  timeout_s: float | None = None,
                  pedestrians: PedestrianPlan | None = None,
                  lefthand: bool = False) -> BuiltNetwork:
    """Write plain XML for ``plan`` into ``out_dir`` and run netconvert to ``<name>.net.xml``
    (killed after ``timeout_s`` seconds).

    :param pedestrians: sidewalks already in ``plan`` and the crossings to build
        (:func:`.pedestrians.plan_pedestrians`); walking areas are built then. None: no
        pedestrian network (the default conversion).
    :param lefthand: traffic keeps left (netconvert ``--lefthand``: junction logic, turn
        directions and SUMO's drivers for left-hand traffic;
        :func:`magail_sumo.scene.driving_side.driving_side`).
    :param name: file name stem; default :func:`magail_sumo.outputs.safe_name` of the scene id
        (the id itself for every real WOMD id), so a scenario id never becomes a path.
    """
    prefix = inside(out_dir, name or safe_name(scene.scenario_id))
    types = node_types(scene, plan)
    plain = write_plain(plan, types, prefix,
                        crossing_xml(pedestrians) if pedestrians is not None else "",
                        walking=pedestrians is not None)
    net = BundleLayout(Path(out_dir), prefix.name).net
    options = list(NETCONVERT_OPTIONS)
    if pedestrians is not None:
        k = options.index("--walkingareas")
        options[k:k + 2] = NETCONVERT_WALKING
    if lefthand:
        options += ["--lefthand", "true"]
    # run in out_dir with bare file names: the net's header comment names no (temporary) folder
    warnings = run_tool("netconvert", [
        "--node-files", plain[0].name, "--edge-files", plain[1].name,
        "--connection-files", plain[2].name, "--output-file", net.name, *options],
        cwd=Path(out_dir), timeout_s=timeout_s)
    return BuiltNetwork(net, plain, types, warnings)


_ = quoteattr  # ids are generated (letters and digits), no escaping needed
