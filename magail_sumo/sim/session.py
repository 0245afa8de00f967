"""One SUMO simulation driven in-process through libsumo.

libsumo runs one simulation per process; :class:`SumoSession` enforces that and wraps every
SUMO failure into :class:`SimulationError` (a clear one-line message, never a hang). Bulk
vehicle state comes from libsumo subscriptions, returned as arrays in the scene frame
(see :mod:`magail_sumo.sim.frames`).
"""

from __future__ import annotations

import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from magail_sumo.errors import MagailSumoError
from magail_sumo.scene.types import STEP_LENGTH, ObjectType
from magail_sumo.sim.frames import centre_to_front, front_to_centre, sumo_angle_to_yaw, yaw_to_sumo_angle
from magail_sumo.sim.sumo_config import SumoConfigError, SumoInputs, read_config




class SimulationError(MagailSumoError):
    """SUMO could not start or failed during a run."""


def _libsumo():
    import libsumo  # imported lazily: it loads the SUMO shared library

    return libsumo


@dataclass(frozen=True)
class VehicleArrays:
    """Vehicles present in SUMO at one step (V = number of vehicles), scene frame.

    :param ids: SUMO vehicle ids.
    :param x, y: (V,) box centre (m).
    :param yaw: (V,) heading (rad, CCW from +x).
    :param speed: (V,) m/s.
    :param length, width: (V,) m.
    :param edge: road (edge) id of each vehicle ("" when off the network).
    """

    ids: tuple[str, ...]
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    length: np.ndarray
    width: np.ndarray
    edge: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.ids)


@dataclass
class SessionConfig:
    """How SUMO is started. An option set to None is not passed: the ``.sumocfg``'s value, or
    SUMO's default, holds (a run that must match the ``sumo`` binary on the same config).

    :param step_length: seconds per step.
    :param seed: SUMO's random seed.
    :param time_to_teleport: -1 disables SUMO's teleporting of jammed vehicles.
    :param collision_action: SUMO's reaction to collisions ("warn": report, keep both).
    :param extra_args: further SUMO command-line options.
    :param subscribe: subscribe every vehicle to the bulk state of :meth:`SumoSession.vehicles`;
        False for a run that only queries through :attr:`SumoSession.api` (lighter, and a
        caller may then remove vehicles through the api freely).
    """

    step_length: float | None = STEP_LENGTH
    seed: int | None = 0
    time_to_teleport: float | None = -1
    collision_action: str | None = "warn"
    extra_args: Sequence[str] = field(default_factory=tuple)
    subscribe: bool = True


_ACTIVE: list["SumoSession"] = []
_WALKING_AREA = re.compile(r":.+_w[0-9]+$")  #: SUMO's ids of walking areas
_SUBSCRIBED_VARS: tuple[int, ...] = ()


class SumoSession:
    """A running SUMO simulation of a configuration (or a net file plus route files).

    SUMO is never given the configuration itself: it is read by
    :func:`~magail_sumo.sim.sumo_config.read_config` (inputs checked; outputs, logs and ports
    dropped) and the command line built from what it kept (:meth:`command`). libsumo never
    listens on a port. Use as a context manager, or call :meth:`start` / :meth:`close`.

    :param sumocfg: a SUMO configuration file (any name, flat or sectioned).
    :param inputs: the configuration already read (:class:`SumoInputs`), e.g. by an env that
        starts many sessions of one scenario; takes the place of ``sumocfg``.
    """

    def __init__(self, sumocfg: str | Path | None = None, *, net: str | Path | None = None,
                 routes: Sequence[str | Path] = (), config: SessionConfig | None = None,
                 inputs: SumoInputs | None = None) -> None:
        if sumocfg is None and net is None and inputs is None:
            raise ValueError("give a .sumocfg, its SumoInputs or a net file")
        self.sumocfg = Path(sumocfg) if sumocfg is not None else (
            inputs.source if inputs is not None else None)
        self.inputs = inputs
        self.net = Path(net) if net is not None else None
        self.routes = [Path(r) for r in routes]
        self.config = config or SessionConfig()
        self.time = 0.0
        self._running = False
        self._walkable: bool | None = None
        self._walk_edge: str | None = None
        self._private: tempfile.TemporaryDirectory | None = None
        self._copies: dict[Path, Path] = {}

    # ------------------------------------------------------------------ lifecycle
    def _overrides(self) -> dict[str, str]:
        """The session's own options (those not None) and ``extra_args`` (option-value
        pairs), by option name; they replace a configuration's values."""
        cfg = self.config
        out = {name: str(value) for name, value in (
            ("step-length", cfg.step_length), ("seed", cfg.seed),
            ("time-to-teleport", cfg.time_to_teleport),
            ("collision.action", cfg.collision_action)) if value is not None}
        extra = list(cfg.extra_args)
        if len(extra) % 2 or any(not str(a).startswith("--") for a in extra[::2]):
            raise ValueError(f"extra_args must be '--option value' pairs, got {extra}")
        out.update((str(k)[2:], str(v)) for k, v in zip(extra[::2], extra[1::2]))
        return {**out, "no-step-log": "true", "no-warnings": "true"}

    def command(self) -> list[str]:
        """The SUMO command line this session starts (reads the configuration when not read
        yet; :class:`SimulationError` when it cannot be used)."""
        if self.inputs is None and self.sumocfg is not None:
            try:
                self.inputs = read_config(self.sumocfg)
            except SumoConfigError as exc:
                raise SimulationError(str(exc)) from None
        cmd = ["sumo"]
        if self.inputs is not None:
            return cmd + self.inputs.args(self._overrides(), self._copies)
        cmd += ["--net-file", str(self.net)]
        if self.routes:
            cmd += ["--route-files", ",".join(str(r) for r in self.routes)]
        for name, value in self._overrides().items():
            cmd += [f"--{name}", value]
        return cmd

    def _check_inputs(self) -> None:
        for label, path in (("network", self.net), *(("routes", r) for r in self.routes)):
            if path is not None and not path.is_file():
                raise SimulationError(f"{path}: SUMO {label} file not found")

    def start(self) -> "SumoSession":
        if self._running:
            return self
        if _ACTIVE:
            raise SimulationError("a SUMO simulation is already running in this process "
                                  "(libsumo allows one; use one worker process per simulation)")
        self._check_inputs()
        command = self.command()
        if self.inputs is not None and self.inputs.cleaned:
            self._private = tempfile.TemporaryDirectory(prefix="magail_sumo_inputs_")
            self._copies = self.inputs.materialise(self._private.name)
            command = self.command()
        ls = _libsumo()
        try:
            ls.start(command)
        except Exception as exc:  # libsumo raises its own exception types
            self._drop_private()
            target = self.sumocfg or self.net
            raise SimulationError(f"{target}: SUMO failed to start: {_one_line(exc)}") from None
        self._running = True
        _ACTIVE.append(self)
        self.time = float(ls.simulation.getTime())
        if self.config.subscribe:
            for vid in ls.vehicle.getIDList():  # vehicles of a loaded state are there already
                ls.vehicle.subscribe(vid, self._variables())
        return self

    @staticmethod
    def _variables() -> tuple[int, ...]:
        ls = _libsumo()
        return (ls.VAR_POSITION, ls.VAR_ANGLE, ls.VAR_SPEED, ls.VAR_LENGTH, ls.VAR_WIDTH,
                ls.VAR_ROAD_ID)

    def _drop_private(self) -> None:
        if self._private is not None:
            self._private.cleanup()
            self._private, self._copies = None, {}

    def close(self) -> None:
        if not self._running:
            self._drop_private()
            return
        try:
            _libsumo().close()
        except Exception:  # closing after a failure: nothing more to report
            pass
        self._running = False
        _ACTIVE.remove(self)
        self._drop_private()

    @property
    def api(self):
        """The running simulation's TraCI-compatible domains (``api.vehicle``, ``api.lane``,
        ``api.simulation``, ...), for the queries this class does not wrap. Modules outside
        :mod:`magail_sumo.sim` reach SUMO only through a session, never by importing libsumo
        (as sumo-rl's env holds its connection); raises when the session is not running."""
        if not self._running:
            raise SimulationError("the SUMO session is not running (call start() first)")
        return _libsumo()

    def walkable(self) -> bool:
        """Whether the network has walking areas (SUMO ids ``:<junction>_w<k>``), i.e. walking
        lanes joined at junctions: a bundle converted with pedestrians; cached."""
        if self._walkable is None:
            self._walkable = any(_WALKING_AREA.match(e) for e in self.api.edge.getIDList())
        return self._walkable

    @property
    def walk_edge(self) -> str:
        """A sidewalk edge (a normal edge with a lane only pedestrians may use; "" when none):
        where a person is added when the walking lane nearest to it is a crossing or walking
        area (SUMO crashes on a person departing there); ``person.moveToXY`` then moves it."""
        if self._walk_edge is None:
            ls = self.api
            self._walk_edge = next((lane.rsplit("_", 1)[0] for lane in ls.lane.getIDList()
                                    if not lane.startswith(":")
                                    and ls.lane.getAllowed(lane) == ("pedestrian",)), "")
        return self._walk_edge

    def __enter__(self) -> "SumoSession":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ stepping
    def step(self) -> tuple[list[str], list[str]]:
        """Advance one step; returns (departed ids, arrived ids) of that step."""
        ls = _libsumo()
        try:
            ls.simulationStep()
            departed = list(ls.simulation.getDepartedIDList())
            arrived = list(ls.simulation.getArrivedIDList())
        except Exception as exc:
            self.close()
            raise SimulationError(f"SUMO failed at t={self.time:.1f} s: {_one_line(exc)}") from None
        self.time = float(ls.simulation.getTime())
        if self.config.subscribe:
            var = self._variables()
            for vid in departed:
                if not vid.startswith(OBSTACLE_PREFIX):
                    ls.vehicle.subscribe(vid, var)
        return departed, arrived

    def vehicles(self) -> VehicleArrays:
        """State of every vehicle in the simulation now, as arrays (scene frame)."""
        ls = _libsumo()
        res = ls.vehicle.getAllSubscriptionResults()
        ids = tuple(res)
        n = len(ids)
        pos = np.empty((n, 2))
        ang = np.empty(n)
        speed = np.empty(n)
        length = np.empty(n)
        width = np.empty(n)
        edges = []
        P, A, S, L, W, R = (ls.VAR_POSITION, ls.VAR_ANGLE, ls.VAR_SPEED, ls.VAR_LENGTH,
                            ls.VAR_WIDTH, ls.VAR_ROAD_ID)
        # libsumo hands subscription results back as one dict per vehicle: unpacking them is the
        # one per-vehicle loop here (~1 µs a vehicle; 0.5 ms for 400, next to ~2 ms of SUMO step)
        for k, vid in enumerate(ids):
            r = res[vid]
            pos[k] = r[P]
            ang[k] = r[A]
            speed[k] = r[S]
            length[k] = r[L]
            width[k] = r[W]
            edges.append(r[R])
        yaw = sumo_angle_to_yaw(ang)
        cx, cy = front_to_centre(pos[:, 0], pos[:, 1], yaw, length)
        return VehicleArrays(ids, cx, cy, yaw, speed, length, width, tuple(edges))

    def remove(self, vid: str) -> None:
        """Take a vehicle out of the simulation (no-op when it already left or never entered).

        Its subscription goes first: libsumo fails the next step ("Vehicle ... is not known")
        when a subscribed vehicle is removed.
        """
        ls = _libsumo()
        try:
            ls.vehicle.unsubscribe(vid)
            ls.vehicle.remove(vid)
        except Exception:  # libsumo raises its own types; already gone is fine
            pass

    def move(self, ids: Sequence[str], x: np.ndarray, y: np.ndarray, yaw: np.ndarray,
             length: np.ndarray, edges: Sequence[str] | None = None,
             lanes: Sequence[int] | None = None, match_threshold: float = 5.0,
             keep_route: int = 2) -> None:
        """Place vehicles at box-centre poses for the next step (``moveToXY``).

        SUMO searches every lane within ``match_threshold`` metres of the target to attach the
        vehicle to; its default (100 m) costs ~300 µs per call on a real converted junction,
        5 m about 20 µs. With keepRoute=2 the vehicle still lands exactly on the target when no
        lane is that close (a vehicle driven off the road; tested).

        :param edges, lanes: optional map-matching hints (edge id, lane index) per vehicle.
        :param keep_route: ``moveToXY``'s keepRoute: 2 maps onto any lane (SUMO may replace the
            vehicle's route by the edge it lands on); 3 (2 + keep the route) maps onto the
            lanes of the vehicle's route only, so the signals and junction foes SUMO gives
            for it stay those of its route; a vehicle 3 cannot place (off its route) is placed
            with 2.
        """
        ls = _libsumo()
        fx, fy = centre_to_front(np.asarray(x), np.asarray(y), np.asarray(yaw), length)
        angle = yaw_to_sumo_angle(np.asarray(yaw))
        for k, vid in enumerate(ids):  # libsumo moves one vehicle per call (~20 µs each)
            edge = edges[k] if edges is not None else ""
            lane = lanes[k] if lanes is not None else -1
            try:
                try:
                    ls.vehicle.moveToXY(vid, edge, lane, float(fx[k]), float(fy[k]),
                                        float(angle[k]), keep_route, match_threshold)
                except Exception:  # libsumo raises its own types
                    if keep_route == 2:
                        raise
                    ls.vehicle.moveToXY(vid, edge, lane, float(fx[k]), float(fy[k]),
                                        float(angle[k]), 2, match_threshold)
            except Exception as exc:
                raise SimulationError(f"moving vehicle {vid} failed at t={self.time:.1f} s: "
                                      f"{_one_line(exc)}") from None


OBSTACLE_PREFIX = "obstacle:"  #: SUMO id prefix of :class:`Obstacles` vehicles
OBSTACLE_MATCH = 1.5  #: m, an obstacle blocks a lane when its front is this close to its centre
PERSON_PREFIX = "walker:"  #: SUMO id prefix of the persons of pedestrian obstacles
PERSON_MATCH = 3.0  #: m, farthest a pedestrian walks in SUMO from a walking lane
PEDESTRIAN = int(ObjectType.PEDESTRIAN)
#: vClass of obstacles on a walkable network: allowed on every vehicle lane, on no walking lane
#: (``converters.sumo.pedestrians.OBSTACLE_CLASS``; SUMO crashes on a vehicle on a crossing)
WALKABLE_OBSTACLE_CLASS = "custom1"
_NO_ANGLE = -1073741824.0  # libsumo's INVALID_DOUBLE_VALUE: map by distance only


class Obstacles:
    """Road users SUMO does not drive (pedestrians, vehicles parked off the lane network, route
    vehicles not yet inserted), shown to SUMO's car-following as vehicles placed each step.

    Each obstacle is a SUMO vehicle of vClass ``ignoring`` (allowed on every lane; on a walkable
    network :data:`WALKABLE_OBSTACLE_CLASS`, kept off its walking lanes) with the
    recorded box, id ``obstacle:<id>``. :meth:`place` puts it at its box-centre pose for the
    next step (``moveToXY``, keepRoute=0) on the lane whose centre line lies within
    :data:`OBSTACLE_MATCH` m of its front: SUMO drivers on that lane then brake for it like for
    a leader (their own gap ``minGap``), drivers on other lanes pass it. An obstacle off every
    lane (on a sidewalk, in a parking bay) is taken out of SUMO until it comes back onto one,
    so it never blocks a lane it does not touch. SUMO's speed of a placed obstacle is its moved
    distance per step. Obstacles are not subscribed: :meth:`SumoSession.vehicles` leaves them out.

    On a network with walking lanes (a bundle converted with ``ConvertOptions.pedestrians``:
    sidewalks, crossings, walking areas; :meth:`SumoSession.walkable`), each obstacle of kind
    ``ObjectType.PEDESTRIAN`` (``kinds``) is also a SUMO person ``walker:<id>`` placed at the
    same pose each step (``person.moveToXY``, keepRoute=0, on the walking lane within
    :data:`PERSON_MATCH` m; none that close: taken out until it comes back). SUMO's junction
    model then makes drivers yield to it on and before a crossing; the vehicle obstacle still
    stops drivers on its lane (a pedestrian crossing off a crosswalk). Elsewhere (and without
    ``kinds``) obstacles behave as above.
    """

    def __init__(self, session: "SumoSession", ids: Sequence[str], length: np.ndarray,
                 width: np.ndarray, match_threshold: float = OBSTACLE_MATCH,
                 kinds: np.ndarray | None = None) -> None:
        self.session = session
        self.threshold = match_threshold
        self.ids: list[str] = []
        self.length = np.zeros(0)
        self.width = np.zeros(0)
        self._gen: list[int] = []  # a removed obstacle comes back under a fresh SUMO id
        self._placed: list[bool] = []
        self._retired: set[int] = set()
        self._miss = np.zeros((0, 2))  # front position last found off every lane (NaN: none)
        self._route = f"{OBSTACLE_PREFIX}route"
        self._walker = np.zeros(0, bool)  # also a SUMO person (module doc)
        self._person: dict[int, str] = {}  # obstacle -> SUMO id of its person now in SUMO
        self._person_gen: dict[int, int] = {}
        self._person_miss = np.zeros((0, 2))  # position last found off every walking lane
        self.add(ids, length, width, kinds)

    def add(self, ids: Sequence[str], length: np.ndarray, width: np.ndarray,
            kinds: np.ndarray | None = None) -> None:
        """More obstacles (recorded box length and width in m; ``kinds``: their
        :class:`~magail_sumo.scene.ObjectType` values, pedestrians walk as persons on a walkable
        network)."""
        ls = _libsumo()
        if len(ids) and self._route not in ls.route.getIDList():
            ls.route.add(self._route, [next(e for e in ls.edge.getIDList()
                                            if not e.startswith(":"))])
        start = len(self.ids)
        for i in ids:  # an id seen before (a vehicle back as an obstacle) gets a fresh name
            name, n = str(i), 1
            while name in self.ids:
                name, n = f"{i}~{n}", n + 1
            self.ids.append(name)
        self.length = np.r_[self.length, np.maximum(np.asarray(length, np.float64), 0.3)]
        self.width = np.r_[self.width, np.maximum(np.asarray(width, np.float64), 0.3)]
        self._gen += [0] * len(ids)
        self._placed += [False] * len(ids)
        self._miss = np.r_[self._miss, np.full((len(ids), 2), np.nan)]
        walker = np.zeros(len(ids), bool)
        if kinds is not None and len(ids):
            walker = np.asarray(kinds) == PEDESTRIAN
            if walker.any() and not self.session.walkable():
                walker[:] = False
        self._walker = np.r_[self._walker, walker]
        self._person_miss = np.r_[self._person_miss, np.full((len(ids), 2), np.nan)]
        vclass = WALKABLE_OBSTACLE_CLASS if len(ids) and self.session.walkable() else "ignoring"
        for k in range(start, len(self.ids)):
            vt = f"{OBSTACLE_PREFIX}{self.ids[k]}"
            ls.vehicletype.copy("DEFAULT_VEHTYPE", vt)
            ls.vehicletype.setVehicleClass(vt, vclass)
            ls.vehicletype.setLength(vt, float(self.length[k]))
            ls.vehicletype.setWidth(vt, float(self.width[k]))
            ls.vehicletype.setMinGap(vt, 0.5)
            self._add(k)

    def sumo_id(self, k: int) -> str:
        return f"{OBSTACLE_PREFIX}{self.ids[k]}" + (f"#{self._gen[k]}" if self._gen[k] else "")

    def _add(self, k: int) -> None:
        # a far departure: only moveToXY inserts it (SUMO never departs it on its own)
        _libsumo().vehicle.add(self.sumo_id(k), self._route, f"{OBSTACLE_PREFIX}{self.ids[k]}",
                               depart="1e9")

    def retire(self, ids: Sequence[str]) -> None:
        """Take obstacles out of SUMO for good (e.g. a route vehicle that SUMO now drives)."""
        ls = _libsumo()
        for k, oid in enumerate(self.ids):
            if oid in ids and k not in self._retired:
                self._retired.add(k)
                try:
                    ls.vehicle.remove(self.sumo_id(k))
                except Exception:  # never placed: dropped from the insertion queue all the same
                    pass
                self._remove_person(k)

    def persons(self) -> dict[str, str]:
        """Obstacle id -> SUMO person id of the pedestrians walking in SUMO now."""
        return {self.ids[k]: pid for k, pid in self._person.items()}

    def _remove_person(self, k: int) -> None:
        pid = self._person.pop(k, None)
        if pid is not None:
            try:
                _libsumo().person.remove(pid)
            except Exception:  # already gone
                pass

    def _place_persons(self, fx: np.ndarray, fy: np.ndarray, angle: np.ndarray) -> None:
        """Persons of the pedestrian obstacles at their poses (front ``fx, fy``; see the class
        doc); a NaN position or no walking lane within :data:`PERSON_MATCH` m takes it out."""
        ls = _libsumo()
        for k in np.flatnonzero(self._walker).tolist():  # one libsumo call per person
            x, y = float(fx[k]), float(fy[k])
            if k in self._retired or not (np.isfinite(x) and np.isfinite(y)):
                self._remove_person(k)
                continue
            if k not in self._person and abs(x - self._person_miss[k, 0]) < 0.01 \
                    and abs(y - self._person_miss[k, 1]) < 0.01:
                continue  # standing where no walking lane was found
            pid = self._person.get(k)
            try:
                if pid is None:
                    edge, pos, _ = ls.simulation.convertRoad(x, y, False, "pedestrian")
                    if edge.startswith(":"):  # no departure inside a junction
                        edge, pos = self.session.walk_edge, 0.0
                    gen = self._person_gen.get(k, 0)
                    self._person_gen[k] = gen + 1
                    pid = f"{PERSON_PREFIX}{self.ids[k]}" + (f"#{gen}" if gen else "")
                    ls.person.add(pid, edge, max(float(pos), 0.0), depart=-3)  # -3: now
                    ls.person.appendWaitingStage(pid, 1e9)
                    self._person[k] = pid
                ls.person.moveToXY(pid, "", x, y, float(angle[k]), 0, PERSON_MATCH)
            except Exception:  # no walking lane that close: not in SUMO's way
                self._person_miss[k] = x, y
                self._remove_person(k)

    def place(self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> int:
        """Place every obstacle at box-centre poses (scene frame) for the next step; NaN
        positions take it out. Returns how many are on a lane."""
        ls = _libsumo()
        fx, fy = centre_to_front(np.asarray(x, np.float64), np.asarray(y, np.float64),
                                 np.asarray(yaw, np.float64), self.length)
        if self._walker.any():  # a pedestrian's centre and navigation angle
            self._place_persons(np.asarray(x, np.float64), np.asarray(y, np.float64),
                                yaw_to_sumo_angle(np.asarray(yaw, np.float64)))
        on = 0
        for k in range(len(self.ids)):  # libsumo moves one vehicle per call (~20 µs each)
            if k in self._retired:
                continue
            if not self._placed[k] and abs(fx[k] - self._miss[k, 0]) < 0.01 \
                    and abs(fy[k] - self._miss[k, 1]) < 0.01:
                continue  # standing where no lane was found (a parked car off the network)
            try:
                if not (np.isfinite(fx[k]) and np.isfinite(fy[k])):
                    raise ValueError("no position")
                ls.vehicle.moveToXY(self.sumo_id(k), "", -1, float(fx[k]), float(fy[k]),
                                    _NO_ANGLE, 0, self.threshold)
                self._placed[k] = True
                on += 1
            except Exception:  # no lane within the threshold: not in SUMO's way
                self._miss[k] = fx[k], fy[k]
                if self._placed[k]:
                    try:
                        ls.vehicle.remove(self.sumo_id(k))
                    except Exception:
                        pass
                    self._placed[k] = False
                    self._gen[k] += 1
                    self._add(k)
        return on


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__
