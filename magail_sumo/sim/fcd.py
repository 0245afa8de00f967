"""SUMO floating car data (FCD) of a run, and a ``.sumocfg`` that replays it in ``sumo-gui``.

libsumo runs cannot show a GUI, so a run (an env episode, an evaluation rollout, a training
episode) is recorded as SUMO FCD and replayed afterwards: ``sumo-gui -c replay.sumocfg``.

* :class:`FcdRecorder` collects poses: :meth:`~FcdRecorder.add` takes one step's arrays over all
  objects at once, :meth:`~FcdRecorder.add_tracks` a whole (A, T) trajectory array.
* :meth:`FcdRecorder.write_fcd` writes SUMO's FCD format (``<fcd-export><timestep time="s">
  <vehicle id x y angle type speed pos lane slope/>``): ``x, y`` the front bumper (SUMO's
  vehicle position; the recorder is given box centres) in the network's (= the
  recording's) frame (m), ``angle`` SUMO's navigation angle (degrees clockwise
  from north: ``(90 - deg(yaw)) mod 360``), ``speed`` (m/s; given, else the distance to the
  object's neighbouring record over the time between them), ``lane``/``pos`` the nearest
  normal (non-junction) lane of the network and the position along it (m) when a network is
  given.
* :func:`write_replay` writes the FCD, a vType file (one type per object: its size, a GUI
  shape by object type and a colour by who drove it: policy agent green, SUMO blue, log
  replay grey) and a ``.sumocfg`` on the converted network (with its signal programs) that
  replays the FCD through SUMO's ``fcd-replay`` device (``--device.fcd-replay.files``): each
  recorded object becomes a vehicle inserted at its first record and moved to every recorded
  pose (``moveToXY``, off the lanes too); one step after its last record it is moved to the end
  of its lane, where it leaves the simulation (the device keeps a vehicle driving until the end
  of its route). So SUMO and ``sumo-gui`` show the vehicles where the run had them; ``sumo
  -c`` of the same file with ``--fcd-output`` reproduces the recorded positions except at each
  object's first step (inserted at its lane position) and that exit step.

An object missing for some steps in the middle of its records drives on in the replay until it
is recorded again (or leaves at the end of its lane).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Sequence
from xml.sax.saxutils import quoteattr

import numpy as np

from magail_sumo.outputs import atomic_write, write_text
from magail_sumo.scene.types import STEP_LENGTH
from magail_sumo.sim.sumo_map import network_map

#: who moved an object in the run (its colour in the replay, R,G,B)
KIND_COLORS: dict[str, str] = {"agent": "60,200,90", "sumo": "70,130,230", "log": "170,170,170"}
#: sumo-gui shapes by scene object type (:class:`~magail_sumo.scene.ObjectType` values)
SHAPES: dict[int, str] = {1: "passenger", 2: "pedestrian", 3: "bicycle"}
_CHUNK = 2_000_000  #: records x lane segments per block of the nearest-lane search


def nav_angle(yaw: np.ndarray) -> np.ndarray:
    """SUMO navigation angle (degrees clockwise from north, [0, 360)) of a yaw (rad CCW from
    +x)."""
    return np.mod(90.0 - np.degrees(np.asarray(yaw, np.float64)), 360.0)


class LaneIndex:
    """Nearest normal lane of a SUMO network for many points at once (numpy; brute force over
    lane segments in blocks)."""

    def __init__(self, net_file: str | PathLike) -> None:
        nm = network_map(net_file)
        a, b, lane, start = [], [], [], []
        ids = []
        for ln, lid in zip(nm.roadmap.lanes, nm.lane_ids):
            if lid.startswith(":"):  # junction-internal: SUMO cannot depart or route there
                continue
            p = np.asarray(ln.polyline, np.float64)[:, :2]
            seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
            a.append(p[:-1])
            b.append(p[1:])
            lane.append(np.full(len(seg), len(ids)))
            start.append(np.concatenate([[0.0], np.cumsum(seg)[:-1]]))
            ids.append(lid)
        self.lane_ids = np.array(ids, dtype=object)
        #: (L,) length of each lane's shape (m)
        self.lane_length = np.array([float(st[-1] + np.linalg.norm(bb[-1] - aa[-1]))
                                     for st, aa, bb in zip(start, a, b)])
        #: (L, 2) end point of each lane's shape
        self.lane_end = np.array([bb[-1] for bb in b]).reshape(-1, 2)
        if ids:
            self._a, self._b = np.concatenate(a), np.concatenate(b)
            self._lane, self._start = np.concatenate(lane), np.concatenate(start)
        else:
            self._a = self._b = np.zeros((0, 2))
            self._lane, self._start = np.zeros(0, np.int64), np.zeros(0)

    def nearest(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(lane id (object array, "" without lanes), position along the lane (m), that
        lane's length (m)) per point."""
        n = len(x)
        lanes = np.full(n, "", dtype=object)
        pos, length = np.zeros(n), np.zeros(n)
        s = len(self._a)
        if s == 0 or n == 0:
            return lanes, pos, length
        d = self._b - self._a
        dd = np.maximum((d * d).sum(1), 1e-12)
        block = max(1, _CHUNK // s)
        for lo in range(0, n, block):
            px = np.asarray(x[lo:lo + block], np.float64)[:, None]
            py = np.asarray(y[lo:lo + block], np.float64)[:, None]
            t = np.clip(((px - self._a[:, 0]) * d[:, 0] + (py - self._a[:, 1]) * d[:, 1]) / dd,
                        0.0, 1.0)
            dist = np.hypot(self._a[:, 0] + t * d[:, 0] - px, self._a[:, 1] + t * d[:, 1] - py)
            k = np.argmin(dist, axis=1)
            rows = np.arange(len(k))
            lanes[lo:lo + block] = self.lane_ids[self._lane[k]]
            length[lo:lo + block] = self.lane_length[self._lane[k]]
            pos[lo:lo + block] = self._start[k] + t[rows, k] * np.sqrt(dd[k])
        return lanes, pos, length


@dataclass(frozen=True)
class ReplayFiles:
    """What :func:`write_replay` wrote."""

    fcd: Path
    types: Path
    sumocfg: Path
    records: int


class FcdRecorder:
    """Poses of a run, step by step; written as SUMO FCD (see the module doc)."""

    def __init__(self, step_length: float = STEP_LENGTH) -> None:
        self.step_length = float(step_length)
        self._parts: list[tuple] = []
        #: per object id: (kind, shape, length, width) of its first record
        self.objects: dict[str, tuple[str, str, float, float]] = {}

    def __len__(self) -> int:
        return sum(len(p[1]) for p in self._parts)

    def add(self, time: float, ids: Sequence, x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
            length: np.ndarray, width: np.ndarray, kind: Sequence[str] | str = "agent",
            shape: Sequence[str] | str = "passenger", speed: np.ndarray | None = None) -> None:
        """Record the objects present at ``time`` (s): (N,) arrays of box centre (m), yaw
        (rad CCW from +x), size (m); per object who moved it (:data:`KIND_COLORS` keys) and its
        GUI shape; speed (m/s) or None (derived from the positions)."""
        n = len(ids)
        if n == 0:
            return
        self.add_tracks(np.array([time], np.float64), ids,
                        *(np.asarray(v, np.float64).reshape(n, 1) for v in (x, y, yaw)),
                        np.ones((n, 1), bool), length, width, kind, shape,
                        None if speed is None else np.asarray(speed, np.float64).reshape(n, 1))

    def add_tracks(self, times: np.ndarray, ids: Sequence, x: np.ndarray, y: np.ndarray,
                   yaw: np.ndarray, valid: np.ndarray, length: np.ndarray, width: np.ndarray,
                   kind: Sequence[str] | str = "agent", shape: Sequence[str] | str = "passenger",
                   speed: np.ndarray | None = None) -> None:
        """Record A objects over T steps: ``times`` (T,) s; ``x, y, yaw, valid`` (A, T) (only
        valid, finite states are recorded); ``length, width`` (A,) m; ``kind``/``shape`` one
        for all or one per object; ``speed`` (A, T) m/s or None."""
        ids = [str(i) for i in ids]
        a = len(ids)
        kinds = [kind] * a if isinstance(kind, str) else list(kind)
        shapes = [shape] * a if isinstance(shape, str) else list(shape)
        length = np.broadcast_to(np.asarray(length, np.float64), (a,))
        width = np.broadcast_to(np.asarray(width, np.float64), (a,))
        for i, k, s, ln, w in zip(ids, kinds, shapes, length, width):
            if i not in self.objects:
                self.objects[i] = (k if k in KIND_COLORS else "log", s, float(ln), float(w))
        x, y, yaw = (np.asarray(v, np.float64) for v in (x, y, yaw))
        ok = np.asarray(valid, bool) & np.isfinite(x) & np.isfinite(y) & np.isfinite(yaw)
        obj, step = np.nonzero(ok)
        if not obj.size:
            return
        sp = None if speed is None else np.asarray(speed, np.float64)[obj, step]
        h = yaw[obj, step]
        half = 0.5 * length[obj]  # SUMO's x, y: the front bumper
        self._parts.append((np.asarray(times, np.float64)[step], np.asarray(ids, object)[obj],
                            x[obj, step] + half * np.cos(h), y[obj, step] + half * np.sin(h),
                            h, sp))

    # ------------------------------------------------------------------ output
    def _records(self):
        t, ids, x, y, yaw = (np.concatenate([p[i] for p in self._parts]) for i in range(5))
        speed = np.concatenate([np.full(len(p[2]), np.nan) if p[5] is None else p[5]
                                for p in self._parts])
        # sort by object, then time: derive the missing speeds from neighbouring records
        order = np.lexsort((t, ids.astype(str)))
        t, ids, x, y, yaw, speed = (v[order] for v in (t, ids, x, y, yaw, speed))
        same_next = np.zeros(len(t), bool)
        same_next[:-1] = ids[1:] == ids[:-1]
        dist = np.zeros(len(t))
        dt = np.ones(len(t))
        dist[:-1] = np.hypot(np.diff(x), np.diff(y))
        dt[:-1] = np.maximum(np.diff(t), 1e-9)
        fwd = np.where(same_next, dist / dt, np.nan)
        back = np.concatenate([[np.nan], fwd[:-1]])
        derived = np.where(np.isfinite(back), back, np.nan_to_num(fwd))
        speed = np.abs(np.where(np.isfinite(speed), speed, derived))  # SUMO speeds are >= 0
        order = np.lexsort((ids.astype(str), t))  # then by time for the file
        return tuple(v[order] for v in (t, ids, x, y, yaw, speed))

    def type_ids(self) -> dict[str, str]:
        """vType id of each object (``fcd<k>``, k in first-recorded order)."""
        return {i: f"fcd{k}" for k, i in enumerate(self.objects)}

    def write_fcd(self, path: str | PathLike, net_file: str | PathLike | None = None) -> int:
        """Write the FCD file (atomically); returns the number of records. With ``net_file``
        each record gets its nearest normal lane and position along it (the replay device
        needs them to insert and place the vehicles)."""
        types = self.type_ids()
        lines = ['<?xml version="1.0" encoding="UTF-8"?>',
                 "<!-- written by magail_sumo (magail_sumo.sim.fcd) -->", "<fcd-export>"]
        n = 0
        if self._parts:
            t, ids, x, y, yaw, speed = self._records()
            t = np.round(t, 6)  # one <timestep> per recorded time
            n = len(t)
            if net_file is not None:
                index = LaneIndex(net_file)
                lanes, pos, lane_len = index.nearest(x, y)
                # the replay device lets a vehicle drive on after its last record until the
                # end of its route (its last lane): a record a step later at the end of that
                # lane ends it there
                last = np.flatnonzero(_last_of_object(ids, t) & (lanes != ""))
                names = index.lane_ids.astype(str)
                sorter = np.argsort(names)
                lane_k = sorter[np.searchsorted(names, lanes[last].astype(str), sorter=sorter)]
                end = index.lane_end[lane_k]
                t, ids, x, y, yaw, lanes, pos = (np.concatenate([v, extra]) for v, extra in (
                    (t, t[last] + self.step_length), (ids, ids[last]), (x, end[:, 0]),
                    (y, end[:, 1]), (yaw, yaw[last]), (lanes, lanes[last]),
                    (pos, lane_len[last])))
                speed = np.concatenate([speed, np.zeros(last.size)])
                order = np.argsort(t, kind="stable")
                t, ids, x, y, yaw, speed, lanes, pos = (
                    v[order] for v in (t, ids, x, y, yaw, speed, lanes, pos))
                n = len(t)
            else:
                lanes, pos = np.full(n, "", dtype=object), np.zeros(n)
            ang = nav_angle(yaw)
            bounds = np.flatnonzero(np.concatenate([[True], np.diff(t) != 0, [True]]))
            for lo, hi in zip(bounds[:-1], bounds[1:]):
                lines.append(f'    <timestep time="{t[lo]:.2f}">')
                for k in range(lo, hi):
                    lane = f' pos="{pos[k]:.2f}" lane={quoteattr(lanes[k])}' if lanes[k] else ""
                    lines.append(
                        f"        <vehicle id={quoteattr(ids[k])} x=\"{x[k]:.2f}\" "
                        f"y=\"{y[k]:.2f}\" angle=\"{ang[k]:.2f}\" type=\"{types[ids[k]]}\" "
                        f"speed=\"{speed[k]:.2f}\"{lane} slope=\"0.00\"/>")
                lines.append("    </timestep>")
        lines.append("</fcd-export>\n")
        with atomic_write(path, "w") as fh:
            fh.write("\n".join(lines))
        return n

    def write_types(self, path: str | PathLike) -> None:
        """The vTypes of the recorded objects (size, GUI shape, colour by kind) as an
        additional file; vClass ``ignoring`` lets them use every lane."""
        types = self.type_ids()
        lines = ["<additional>"]
        for i, (kind, shape, length, width) in self.objects.items():
            lines.append(f'    <vType id="{types[i]}" vClass="ignoring" guiShape="{shape}" '
                         f'length="{max(length, 0.1):.2f}" width="{max(width, 0.1):.2f}" '
                         f'minGap="0" color="{KIND_COLORS[kind]}"/>')
        lines.append("</additional>\n")
        write_text(path, "\n".join(lines))

    def end_time(self) -> float:
        """Time of the last record (s; 0 when empty)."""
        return max((float(p[0].max()) for p in self._parts), default=0.0)


def _last_of_object(ids: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Boolean mask of each object's latest record."""
    order = np.lexsort((t, ids.astype(str)))
    last = np.zeros(len(t), bool)
    s = ids[order]
    last[order[np.concatenate([s[1:] != s[:-1], [True]])]] = True
    return last


def _rel(target: Path, start: Path) -> str:
    """``target`` relative to folder ``start`` when possible (the config stays valid when the
    folders move together), else absolute."""
    t, s = target.resolve(), start.resolve()
    try:
        if os.path.commonpath([t, s]) != t.anchor:
            return os.path.relpath(t, s)
    except ValueError:  # another drive (Windows)
        pass
    return str(t)


def replay_paths(fcd: str | PathLike) -> tuple[Path, Path, Path]:
    """(FCD, vType file, sumocfg) paths for an FCD path: ``NAME.fcd.xml`` (``.fcd.xml`` added
    when missing) beside ``NAME.types.add.xml`` and ``NAME.sumocfg``."""
    p = Path(fcd)
    stem = p.name[:-len(".fcd.xml")] if p.name.endswith(".fcd.xml") else \
        (p.name[:-4] if p.name.endswith(".xml") else p.name)
    return (p.with_name(stem + ".fcd.xml"), p.with_name(stem + ".types.add.xml"),
            p.with_name(stem + ".sumocfg"))


def write_replay(recorder: FcdRecorder, fcd: str | PathLike, net_file: str | PathLike,
                 additional: Sequence[str | PathLike] = ()) -> ReplayFiles:
    """Write the FCD, its vTypes and a ``.sumocfg`` replaying it on ``net_file`` (plus
    ``additional`` files, e.g. the bundle's signal programs) in ``sumo-gui`` (or ``sumo``):
    see the module doc. Paths in the config are relative to its folder when possible. All
    files are written atomically; the folder is made when missing."""
    fcd_path, types_path, cfg_path = replay_paths(fcd)
    cfg_path.parent.mkdir(parents=True, exist_ok=True)
    net = Path(net_file)
    n = recorder.write_fcd(fcd_path, net)
    recorder.write_types(types_path)
    folder = cfg_path.parent
    adds = [_rel(Path(a), folder) for a in additional] + [types_path.name]
    end = recorder.end_time() + 2 * recorder.step_length
    cfg = f"""<?xml version="1.0" encoding="UTF-8"?>
<!-- sumo-gui -c {cfg_path.name}: replays {fcd_path.name} (written by magail_sumo) -->
<configuration>
    <input>
        <net-file value={quoteattr(_rel(net, folder))}/>
        <additional-files value={quoteattr(",".join(adds))}/>
    </input>
    <time>
        <begin value="0"/>
        <end value="{end:.2f}"/>
        <step-length value="{recorder.step_length:g}"/>
    </time>
    <processing>
        <insertion-checks value="none"/>
        <collision.action value="none"/>
        <ignore-route-errors value="true"/>
        <time-to-teleport value="-1"/>
    </processing>
    <fcd_replay>
        <device.fcd-replay.files value={quoteattr(fcd_path.name)}/>
    </fcd_replay>
    <report>
        <no-warnings value="true"/>
        <no-step-log value="true"/>
    </report>
    <gui_only>
        <delay value="{1000 * recorder.step_length:.0f}"/>
    </gui_only>
</configuration>
"""
    write_text(cfg_path, cfg)
    return ReplayFiles(fcd_path, types_path, cfg_path, n)
