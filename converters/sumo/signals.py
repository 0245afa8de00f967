"""Traffic-light programs that replay the recorded per-step signal states of the lanes.

Each link of a SUMO traffic light is traced back to the WOMD junction lanes of its connection;
the first signalled one gives its state at every step (UNKNOWN keeps the last known state,
steps before the first known state keep the first known one). Equal consecutive steps merge
into one phase of ``run * dt`` seconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from magail_sumo.scene import Scene, SignalState

from .topology import NetworkPlan

#: SUMO link state per WOMD state ('g' for GO on a permissive left is decided per link).
SUMO_CHAR = {SignalState.ARROW_STOP: "r", SignalState.ARROW_CAUTION: "y",
             SignalState.ARROW_GO: "G", SignalState.STOP: "r", SignalState.CAUTION: "y",
             SignalState.GO: "G", SignalState.FLASHING_STOP: "s",
             SignalState.FLASHING_CAUTION: "o"}
#: go / caution / stop class of a SUMO link state character.
CHAR_CLASS = {"G": "go", "g": "go", "y": "caution", "Y": "caution", "o": "caution", "u": "caution",
              "r": "stop", "s": "stop", "O": "off"}
STATE_CLASS = {SignalState.ARROW_STOP: "stop", SignalState.STOP: "stop",
               SignalState.FLASHING_STOP: "stop", SignalState.ARROW_CAUTION: "caution",
               SignalState.CAUTION: "caution", SignalState.FLASHING_CAUTION: "caution",
               SignalState.ARROW_GO: "go", SignalState.GO: "go"}
HOLD_S = 86400.0  #: s, duration of the final phase when the program does not cycle


@dataclass
class SignalPrograms:
    """Programs per traffic light and the link indices of every signalled WOMD lane."""

    states: dict[str, list[str]]  # tls id -> per-step state strings (T,)
    lane_links: dict[int, list[tuple[str, int]]]  # WOMD lane -> [(tls, link index)]
    unmapped_lanes: list[int]


def lane_state_table(scene: Scene) -> dict[int, np.ndarray]:
    """Per signalled lane a (T,) int8 array of states with UNKNOWN filled (last known, then first)."""
    sig = scene.signals
    out: dict[int, np.ndarray] = {}
    for lane in sig.lanes.tolist():
        rows = (sig.lane == lane) & sig.known()
        arr = np.zeros(scene.num_steps, np.int8)
        if rows.any():
            steps, states = sig.step[rows], sig.state[rows]
            idx = np.searchsorted(steps, np.arange(scene.num_steps), side="right") - 1
            arr = states[np.maximum(idx, 0)]
        out[lane] = arr
    return out


def build_programs(scene: Scene, plan: NetworkPlan, net) -> SignalPrograms:
    """Per-step state strings for every traffic light of the built ``net`` (sumolib Net)."""
    table = lane_state_table(scene)
    via_of = {(c.from_edge, c.from_lane, c.to_edge, c.to_lane): c.via for c in plan.connections}
    states: dict[str, list[str]] = {}
    lane_links: dict[int, list[tuple[str, int]]] = {}
    for tls in net.getTrafficLights():
        links = tls.getConnections()  # [in lane, out lane, link index]
        n_links = max((ln[2] for ln in links), default=-1) + 1
        chars = np.full((scene.num_steps, n_links), "O", dtype="<U1")
        for in_lane, out_lane, li in links:
            key = (in_lane.getEdge().getID(), in_lane.getIndex(),
                   out_lane.getEdge().getID(), out_lane.getIndex())
            lane = next((v for v in via_of.get(key, ()) if v in table), None)
            if lane is None:
                continue
            lane_links.setdefault(lane, []).append((tls.getID(), li))
            conn = [c for c in in_lane.getOutgoing() if c.getToLane() is out_lane]
            left = bool(conn) and conn[0].getDirection() in ("l", "L")
            for st in np.unique(table[lane]):
                if st == SignalState.UNKNOWN:
                    continue
                ch = SUMO_CHAR[SignalState(int(st))]
                if left and st == SignalState.GO:
                    ch = "g"
                chars[table[lane] == st, li] = ch
        states[tls.getID()] = ["".join(row) for row in chars]
    unmapped = sorted(set(table) - set(lane_links))
    return SignalPrograms(states, lane_links, unmapped)


def write_programs(path: Path, programs: SignalPrograms, dt: float, cycle: bool) -> None:
    """Write the programs as an additional file (programID ``womd``, static, offset 0).

    With ``cycle`` the recorded sequence repeats past the end of the log; otherwise the last
    state is held.
    """
    with open(path, "w") as fh:
        fh.write("<additional>\n")
        for tls, per_step in programs.states.items():
            fh.write(f'  <tlLogic id="{tls}" type="static" programID="womd" offset="0">\n')
            runs: list[list] = []
            for s in per_step[:1] + per_step:  # one extra step: see baseline.run_baseline
                if runs and runs[-1][0] == s:
                    runs[-1][1] += 1
                else:
                    runs.append([s, 1])
            for k, (s, n) in enumerate(runs):
                dur = n * dt if cycle or k < len(runs) - 1 else n * dt + HOLD_S
                fh.write(f'    <phase duration="{dur:.1f}" state="{s}"/>\n')
            fh.write("  </tlLogic>\n")
        fh.write("</additional>\n")


def unmapped_reason(scene: Scene, plan: NetworkPlan, lane: int) -> str:
    """Why signalled ``lane`` is part of no SUMO traffic-light link, as far as the map says."""
    rec = next((l for l in scene.roadmap.lanes if l.id == lane), None)
    if rec is None or (lane not in plan.lane_edges and lane not in plan.junction_lanes):
        return "signalled lane is not in the built network (not in the map, or dropped)"
    if not rec.entry_lanes and not rec.exit_lanes and lane not in plan.linked:
        return "signalled lane is joined to no other lane in the map: no junction to signal"
    if lane not in plan.junction_lanes:
        return "signalled lane is a road lane, not a junction lane: no junction link to signal"
    return "signalled lane is not part of a traffic-light link"
