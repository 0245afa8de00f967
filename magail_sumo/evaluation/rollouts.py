"""Closed-loop rollouts of recorded scenes under the WOSAC protocol, stored as Parquet.

Protocol: log steps ``0..current_time_index`` are the recorded history; the next 80 steps
(8 s at 0.1 s) are simulated for every object valid at ``current_time_index`` (the official
sim-agent set). Methods:

* ``logreplay``: the recorded future (stored states, invalid ones included).
* ``constvel``: constant velocity from the recorded state at the current step (heading held).
* ``sumo``: SUMO's default car-following (Krauss) drives the converted routes. Route vehicles
  are placed at their recorded pose and speed at the current step, then released (parked
  vehicles, which SUMO holds on its own parking position, keep their recorded pose); each vehicle
  gets a speed factor ~ N(1, 0.1) (clipped to [0.8, 1.2]) drawn from the rollout seed, which
  also seeds SUMO (driver imperfection ``sigma``), so rollouts differ. Every other sim agent
  (pedestrians, objects SUMO does not carry, parked vehicles, route vehicles that depart later
  or whose insertion SUMO refused) moves at constant velocity and is an obstacle in SUMO
  (:class:`~magail_sumo.sim.session.Obstacles`) that SUMO's drivers brake for; a route vehicle
  departing later leaves its obstacle when SUMO inserts it. A route vehicle that reaches the
  last edge of its route (its log ended there, or SUMO drove it faster than the human) keeps
  driving: its route is extended, edge by edge, by the straightest connection from its lane
  (:func:`_continue_routes`); at a dead end inside the mapped area (a driveway or parking aisle
  without a lane) it stops at the lane's end, and only one that reaches the edge of the map
  leaves SUMO and goes on at constant velocity as an obstacle. A route vehicle due at the
  current step or whose insertion SUMO put off (no room at its departure) is inserted at its
  recorded pose at the current step when its route passes within :data:`QUEUED_MATCH` m, else
  it is taken out of SUMO and an obstacle.
* a policy (``random``, or a checkpoint / ``module:factory`` spec, see :func:`make_policy`):
  drives every route vehicle and cyclist through :class:`~magail_sumo.env.SumoDrivingEnv`
  (bicycle model, SUMO co-simulation, no event terminates an agent). Each rollout builds its
  policy with the rollout seed; a training checkpoint samples its actions from that seed
  (``deterministic=True``: the tanh of the Gaussian mean, the same in every rollout).

Objects a method does not move (pedestrians, objects SUMO does not carry, vehicles not yet
inserted) and objects that leave the simulation early (arrived at their route end, end of
their recorded track in the env) follow the constant-velocity model from their last simulated
(else recorded) state. Positions are box centres in the scene frame (m), headings rad CCW
from +x; z is the recorded z at the current step (SUMO is 2-D).

Every SUMO rollout batch runs in a fresh ``spawn`` worker process (libsumo allows one
simulation per process and has crashed when a second one starts after vehicle removals).
"""

from __future__ import annotations

import importlib
import inspect
import json
import math
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Collection, Iterable, Iterator, Protocol

import numpy as np

from magail_sumo.errors import MagailSumoError
from magail_sumo.evaluation.submission import ScenarioRollouts, sim_agent_ids
from magail_sumo.outputs import (NameRegistry, OutputError, atomic_path, claim_output_dir, inside,
                                 one_line, printable, safe_name, write_text)
from magail_sumo.scene import Scene
from magail_sumo.scene.types import STEP_LENGTH
from magail_sumo.sim.dynamics import ACTION_SIZE, wrap_angle

N_STEPS = 80  #: simulated steps per rollout (8 s)
DT = STEP_LENGTH  #: s per step
BASELINES = ("logreplay", "constvel", "sumo")
BUILTIN_POLICIES = ("random",)
SUMO_METHODS = ("sumo",)  #: baselines that need SUMO (worker processes)
COLUMNS = ("scenario_id", "method", "rollout", "object_id", "step", "x", "y", "z", "heading",
           "valid")
SPEED_FACTOR_SD = 0.1
#: m, a route vehicle whose insertion SUMO put off is inserted at its recorded pose at the current
#: step when its route passes this close (else it is an obstacle)
QUEUED_MATCH = 5.0


class EvaluationError(MagailSumoError):
    """A rollout or evaluation input cannot be used (one line naming the scene / agent)."""


# ---------------------------------------------------------------------------------- policies
class Policy(Protocol):
    """What a policy under test provides: normalised ``[accel, steer]`` actions in [-1, 1]² per
    agent from the env's observations (agents named by their WOMD track id).

    Optional extension: a policy with a ``begin(scene, env)`` method is told the scene and the
    :class:`~magail_sumo.env.SumoDrivingEnv` of each rollout right after the env's reset, before
    its first ``act``; during ``act`` it may read the env (``env.t``, ``env.agent_states()`` for
    the live agents' simulated states, ``env.scene`` for the recorded ones of the others) but
    must not step or reset it. Policies without it are driven exactly as before."""

    def act(self, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]: ...


class RandomPolicy:
    """Uniform random actions in [-1, 1]², seeded (agents served in sorted-name order)."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def act(self, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        names = sorted(observations)
        a = self.rng.uniform(-1.0, 1.0, (len(names), ACTION_SIZE)).astype(np.float32)
        return dict(zip(names, a))


#: Checkpoint loaders by file suffix (e.g. ``".pt"``): ``loader(path, seed) -> Policy``; a
#: loader with a ``deterministic`` keyword also gets evaluation's choice (sample the policy with
#: ``seed``, or act deterministically). The training package registers its own;
#: ``module:factory`` specs work without registering.
POLICY_LOADERS: dict[str, Callable[..., Policy]] = {}


def _training_checkpoint(path: Path, seed: int, deterministic: bool = False) -> Policy:
    """``magail-sumo train`` checkpoints (imported lazily: torch / SB3 only when used)."""
    from magail_sumo.training.policy_loader import load_checkpoint_policy

    return load_checkpoint_policy(path, seed, deterministic=deterministic)


POLICY_LOADERS[".pt"] = _training_checkpoint


def _takes_deterministic(loader: Callable) -> bool:
    """Whether ``loader`` accepts a ``deterministic`` keyword."""
    try:
        params = inspect.signature(loader).parameters.values()
    except (TypeError, ValueError):  # no signature to read (a builtin)
        return False
    return any(p.name == "deterministic" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
               or p.kind == p.VAR_KEYWORD for p in params)


def make_policy(spec: str, seed: int, deterministic: bool = False) -> Policy:
    """The policy named by ``spec``: ``random``, ``pretrained`` / ``pretrained:NAME`` (a
    shipped checkpoint, :mod:`magail_sumo.pretrained`; ``$MAGAIL_SUMO_PRETRAINED_DIR`` selects
    another registry folder), a checkpoint file with a registered loader, or
    ``package.module:factory`` (``factory(seed) -> Policy``).

    :param seed: the policy's seed (evaluation passes :func:`rollout_seed`).
    :param deterministic: passed to a checkpoint loader that takes it (a training checkpoint
        then acts with the tanh of its Gaussian mean instead of sampling); ``random`` and
        factories ignore it."""
    if spec == "random":
        return RandomPolicy(seed)
    from magail_sumo.pretrained import is_pretrained_spec, resolve

    if is_pretrained_spec(spec):
        entry = resolve(spec)
        loader = POLICY_LOADERS.get(entry.checkpoint.suffix)
        if loader is None:  # only if a caller unregistered ".pt"
            raise EvaluationError(f"{spec}: no policy loader for '.pt' checkpoints")
        return _checkpoint_policy(spec, loader, entry.checkpoint, seed, deterministic)
    path = Path(spec)
    if path.is_file():
        loader = POLICY_LOADERS.get(path.suffix)
        if loader is None:
            raise EvaluationError(f"{spec}: no policy loader for '{path.suffix}' checkpoints "
                                  "(register one in magail_sumo.evaluation.rollouts.POLICY_LOADERS)")
        return _checkpoint_policy(spec, loader, path, seed, deterministic)
    if ":" in spec:
        mod, _, attr = spec.partition(":")
        try:
            factory = getattr(importlib.import_module(mod), attr)
        except Exception as exc:  # noqa: BLE001 - any import failure of a user module
            raise EvaluationError(f"{spec}: cannot import policy factory "
                                  f"({type(exc).__name__}: {_line(exc)})") from None
        return _built(spec, factory, seed)
    raise EvaluationError(f"{spec}: not a method ({', '.join(BASELINES + BUILTIN_POLICIES)}), "
                          "pretrained[:NAME], a checkpoint file or a module:factory spec")


def _checkpoint_policy(spec: str, loader: Callable, path: Path, seed: int,
                       deterministic: bool) -> Policy:
    if _takes_deterministic(loader):
        return _built(spec, lambda p, s: loader(p, s, deterministic=deterministic), path, seed)
    return _built(spec, loader, path, seed)


def _line(exc: BaseException) -> str:
    return one_line(exc)


def _built(spec: str, factory: Callable, *args) -> Policy:
    """``factory(*args)``; any exception becomes one :class:`EvaluationError` naming ``spec``."""
    try:
        policy = factory(*args)
    except MagailSumoError:
        raise
    except Exception as exc:  # noqa: BLE001 - a user factory / loader may raise anything
        raise EvaluationError(f"policy {spec}: could not be created: "
                              f"{type(exc).__name__}: {_line(exc)}") from None
    if not callable(getattr(policy, "act", None)):
        raise EvaluationError(f"policy {spec}: the factory returned {type(policy).__name__}, "
                              "which has no act(observations) method")
    return policy


def method_name(spec: str) -> str:
    """Name a method is stored under (``evaluate --name`` overrides it): the spec itself for
    built-ins; for a checkpoint in a run's ``checkpoints/`` folder the run folder's name
    (``runs/magail/checkpoints/latest.pt`` -> ``magail``; another file there -> ``magail-<stem>``,
    e.g. ``magail-update_000020``); another file's stem; a factory's name; for
    ``pretrained:NAME`` the registry name ``NAME`` (``pretrained``: the default's name)."""
    if spec in BASELINES + BUILTIN_POLICIES:
        return spec
    from magail_sumo.pretrained import PretrainedError, is_pretrained_spec, name_of

    if is_pretrained_spec(spec):
        try:
            return name_of(spec)
        except PretrainedError:
            return spec.replace(":", "-")
    p = Path(spec)
    if p.is_file():
        run = p.resolve().parent
        if run.name == "checkpoints" and run.parent.name:
            return run.parent.name if p.stem == "latest" else f"{run.parent.name}-{p.stem}"
        return p.stem
    return spec.rpartition(":")[2] or spec


def rollout_seed(seed: int, rollout: int) -> int:
    """Seed of one rollout (SUMO and numpy), from the run seed; < 2**31."""
    return int(np.random.SeedSequence([seed, rollout]).generate_state(1)[0] % (2 ** 31 - 1))


# ------------------------------------------------------------------------- trajectory models
@dataclass
class _Track:
    """Simulated states of the A sim agents over the T simulated steps, NaN where unknown."""

    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray

    @classmethod
    def empty(cls, a: int, t: int = N_STEPS) -> "_Track":
        return cls(*(np.full((a, t), np.nan) for _ in range(4)))


def _current_state(scene: Scene, ids: np.ndarray) -> tuple[np.ndarray, ...]:
    tr = scene.tracks
    row_of = {int(i): k for k, i in enumerate(tr.id.tolist())}
    rows = np.array([row_of[int(i)] for i in ids], np.int64)
    c = scene.current_time_index
    return (rows, tr.x[rows, c], tr.y[rows, c], tr.z[rows, c],
            tr.heading[rows, c].astype(np.float64), tr.vx[rows, c].astype(np.float64),
            tr.vy[rows, c].astype(np.float64))


def fill_constant_velocity(scene: Scene, ids: np.ndarray, track: _Track
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Complete ``track``: unknown steps continue the last known state at constant velocity
    (speed along the heading); before any known state, the recorded state at the current
    step (its velocity vector) is extrapolated. Returns (x, y, yaw), each (A, T)."""
    _, x0, y0, _, h0, vx0, vy0 = _current_state(scene, ids)
    a, t = track.x.shape
    have = np.isfinite(track.x) & np.isfinite(track.y)
    steps = np.arange(t)
    last = np.maximum.accumulate(np.where(have, steps, -1), axis=1)  # (A, T)
    seen = last >= 0
    li = np.maximum(last, 0)
    take = lambda arr: np.take_along_axis(arr, li, 1)  # noqa: E731
    bx = np.where(seen, take(track.x), x0[:, None])
    by = np.where(seen, take(track.y), y0[:, None])
    byaw = np.where(seen, take(track.yaw), h0[:, None])
    sp = np.nan_to_num(take(track.speed))
    vx = np.where(seen, sp * np.cos(byaw), vx0[:, None])
    vy = np.where(seen, sp * np.sin(byaw), vy0[:, None])
    gap = (steps[None] - np.where(seen, last, -1)) * DT  # s since the base state
    return bx + vx * gap, by + vy * gap, byaw


def constant_velocity(scene: Scene, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, yaw) (A, T): recorded state at the current step moved at its velocity."""
    return fill_constant_velocity(scene, ids, _Track.empty(len(ids)))


def _as_rollouts(scene: Scene, ids: np.ndarray, xs: list, ys: list, yaws: list
                 ) -> ScenarioRollouts:
    _, _, _, z0, _, _, _ = _current_state(scene, ids)
    x, y, yaw = (np.stack(v).astype(np.float32) for v in (xs, ys, yaws))
    yaw = wrap_angle(yaw).astype(np.float32)
    z = np.broadcast_to(z0.astype(np.float32)[None, :, None], x.shape).copy()
    return ScenarioRollouts(scene.scenario_id, ids.astype(np.int64), x, y, z, yaw)


# ------------------------------------------------------------------------------ SUMO rollouts
def _departures(folder: Path, sumocfg: Path) -> dict[str, int]:
    """Departure step of every vehicle of a bundle's route file."""
    import xml.etree.ElementTree as ET

    root = ET.parse(Path(folder) / sumocfg.name.replace(".sumocfg", ".rou.xml")).getroot()
    return {v.get("id", ""): int(round(float(v.get("depart", "0")) / DT))
            for v in root.iter("vehicle")}


#: link directions (SUMO ``lane.getLinks``) in the order a continued route prefers them;
#: turnarounds ("t") are never taken
_CONTINUE_ORDER = {"s": 0, "R": 1, "L": 1, "r": 2, "l": 2}


#: m, a dead end (a lane without successor) has mapped road ahead when lane, road-line or
#: road-edge points lie between these distances ahead of the lane's end...
DEAD_END_AHEAD = (2.0, 30.0)
#: m, ...and within this distance to either side of its direction
DEAD_END_HALF_WIDTH = 8.0


def map_points(scene: Scene) -> np.ndarray:
    """(P, 2) points of every lane, road line and road edge of the scene's map (scene frame)."""
    m = scene.roadmap
    parts = [f.polyline[:, :2] for feats in (m.lanes, m.road_lines, m.road_edges) for f in feats]
    return np.concatenate(parts).astype(np.float64) if parts else np.zeros((0, 2))


def _mapped_ahead(shape: np.ndarray, points: np.ndarray) -> bool:
    """Whether ``points`` (P, 2) hold mapped road ahead of the end of a lane of centre line
    ``shape`` (K, 2): :data:`DEAD_END_AHEAD` along its last segment, within
    :data:`DEAD_END_HALF_WIDTH` to the side."""
    d = shape[-1] - shape[-2]
    n = float(np.hypot(*d))
    if n < 1e-6 or not len(points):
        return False
    ux, uy = d / n
    rx, ry = (points - shape[-1]).T
    ahead, side = rx * ux + ry * uy, np.abs(ry * ux - rx * uy)
    lo, hi = DEAD_END_AHEAD
    return bool(np.any((ahead > lo) & (ahead < hi) & (side < DEAD_END_HALF_WIDTH)))


#: m of lanes a continued route is extended by at a time (more than one step's drive: SUMO
#: would otherwise cross a short added edge and arrive within one step)
CONTINUE_AHEAD = 50.0


def _continue_routes(ls, vehicles, ends: dict[str, str], keep: Collection[str] = (),
                     points: np.ndarray | None = None) -> None:
    """Extend the route of every vehicle now on the last edge of its route: edge after edge,
    the successor reached from the lane by the straightest link (:data:`_CONTINUE_ORDER`, then
    the shorter link), until :data:`CONTINUE_AHEAD` m are added or a dead end is reached.
    ``ends`` maps a vehicle to the last edge of its route (filled on first sight, updated when
    extended, "" once it ends for good); vehicles in ``keep`` (parked ones, held at their
    parking stop) keep their routes.

    A lane without a successor (a turnaround aside) is a dead end: where the scene's map goes on
    ahead of it (``points``, :func:`map_points`; :func:`_mapped_ahead`) — the end of a driveway
    or parking aisle the map has no lane for — the vehicle stops at the lane's end and stays
    there (as the humans who drive there park); at the edge of the map it leaves SUMO at the
    lane's end."""
    for vid, edge in zip(vehicles.ids, vehicles.edge):
        if vid in keep:
            continue
        last = ends.get(vid)
        if last is None:
            last = ends[vid] = ls.vehicle.getRoute(vid)[-1]
        if edge != last or not last:
            continue
        lane, added, chain, dead_end = ls.vehicle.getLaneID(vid), 0.0, [edge], False
        while added < CONTINUE_AHEAD:
            links = [ln for ln in ls.lane.getLinks(lane) if ln[6] in _CONTINUE_ORDER]
            if not links:
                dead_end = True  # ``lane`` (on ``chain[-1]``) goes nowhere
                break
            nxt = min(links, key=lambda ln: (_CONTINUE_ORDER[ln[6]], ln[7]))[0]
            if ls.lane.getEdgeID(nxt) in chain:  # a loop
                break
            lane = nxt
            chain.append(ls.lane.getEdgeID(lane))
            added += ls.lane.getLength(lane)
        ends[vid] = chain[-1] if added >= CONTINUE_AHEAD else ""
        try:
            if len(chain) > 1:
                ls.vehicle.setRoute(vid, chain)
            if dead_end and points is not None and _mapped_ahead(
                    np.asarray(ls.lane.getShape(lane)), points):
                ls.vehicle.setStop(vid, chain[-1], max(0.0, ls.lane.getLength(lane) - 0.1),
                                   int(lane.rsplit("_", 1)[1]), duration=1e6)
        except Exception:  # SUMO refused (the class may not use the edge; too close to brake)
            ends[vid] = ""


def _drop(ls, ids, routed: set[str]) -> None:
    """Take route vehicles that have not departed out of SUMO's insertion queue."""
    for i in ids:
        if str(int(i)) in routed:
            try:
                ls.vehicle.remove(str(int(i)))
            except Exception:  # never loaded or already gone
                pass


def _sumo_rollout(scene: Scene, bundle_dir: Path, seed: int) -> tuple[np.ndarray, ...]:
    """One rollout of SUMO's own car-following (see module doc); (x, y, yaw) (A, T)."""
    import libsumo as ls

    from magail_sumo.env.bundle import SceneBundle
    from magail_sumo.sim.frames import centre_to_front, yaw_to_sumo_angle
    from magail_sumo.sim.session import OBSTACLE_PREFIX, Obstacles, SessionConfig, SumoSession

    bundle = SceneBundle.load(scene, bundle_dir)
    ids = sim_agent_ids(scene)
    col = {str(int(i)): k for k, i in enumerate(ids)}
    rows, x0, y0, _, h0, vx0, vy0 = _current_state(scene, ids)
    length = scene.tracks.length[rows, scene.current_time_index].astype(np.float64)
    width = scene.tracks.width[rows, scene.current_time_index].astype(np.float64)
    cur = scene.current_time_index
    rng = np.random.default_rng(seed)
    track = _Track.empty(len(ids))
    held: list[str] = []
    routed = set(bundle.sumo_ids)
    departs = _departures(bundle.folder, bundle.sumocfg)
    due: set[str] = set()
    later: set[str] = set()
    gone: dict[int, int] = {}  # agent -> column of its last state before it left SUMO
    ends: dict[str, str] = {}  # driven vehicle -> last edge of its (continued) route
    points = map_points(scene)
    obstacles: Obstacles | None = None
    obs = np.zeros(0, np.int64)
    ox, oy, oyaw = constant_velocity(scene, ids)  # the future of every agent SUMO does not drive
    with SumoSession(bundle.sumocfg, config=SessionConfig(seed=seed)) as sess:
        for k in range(cur + 1 + N_STEPS):  # after k + 1 steps SUMO shows log step k
            if k == cur:  # start the future from the recorded state: pose and speed
                present = set(ls.vehicle.getIDList())
                # route vehicles whose insertion SUMO has put off (no room at their departure)
                # are inserted at their recorded pose on their route, when it is that close
                queued = {vid for vid in col if vid in routed and vid not in present
                          and vid not in bundle.parked and departs.get(vid, cur) <= cur}
                for vid in sorted(present | queued):
                    a = col.get(vid)
                    if a is None or vid in bundle.parked:
                        continue
                    fx, fy = centre_to_front(x0[a:a + 1], y0[a:a + 1], h0[a:a + 1],
                                             length[a:a + 1])
                    try:
                        ls.vehicle.moveToXY(vid, "", -1, float(fx[0]), float(fy[0]),
                                            float(yaw_to_sumo_angle(h0[a:a + 1])[0]), 1,
                                            100.0 if vid in present else QUEUED_MATCH)
                        ls.vehicle.setSpeed(vid, float(np.hypot(vx0[a], vy0[a])))
                        held.append(vid)
                        present.add(vid)
                    except Exception:  # off its route: SUMO keeps its own state
                        pass
                # every other agent becomes an obstacle SUMO's drivers see: pedestrians,
                # objects SUMO does not carry, parked vehicles (off the lanes in SUMO) and route
                # vehicles not in SUMO yet (those departing later drop theirs when they depart)
                due = {vid for vid in col if departs.get(vid, -1) == cur}  # inserted this step
                later = {vid for vid in col if departs.get(vid, -1) > cur}
                driven = (present | due) - bundle.parked
                obs = np.array([a for vid, a in col.items() if vid not in driven], np.int64)
                _drop(ls, [ids[a] for a in obs], routed - present - later)
                obstacles = Obstacles(sess, [str(int(ids[a])) for a in obs], length[obs],
                                      width[obs])
            elif k == cur + 1 and obstacles is not None:  # insertions SUMO refused at the current step
                now = set(ls.vehicle.getIDList())
                late = np.array([col[vid] for vid in sorted(due - now - bundle.parked)], np.int64)
                if len(late):
                    _drop(ls, [ids[a] for a in late], routed - now)
                    obstacles.add([str(int(ids[a])) for a in late], length[late], width[late])
                    obs = np.r_[obs, late]
            if obstacles is not None and k >= cur:
                t = k - cur - 1  # column of log step k (-1: the current step)
                if t < 0:
                    obstacles.place(x0[obs], y0[obs], h0[obs])
                else:
                    px, py, pyaw = ox[obs, t], oy[obs, t], oyaw[obs, t]
                    for j in np.flatnonzero(np.isin(obs, list(gone))).tolist():
                        a, t0 = int(obs[j]), gone[int(obs[j])]  # on from its last SUMO state
                        d = track.speed[a, t0] * (t - t0) * DT
                        px[j] = track.x[a, t0] + d * np.cos(track.yaw[a, t0])
                        py[j] = track.y[a, t0] + d * np.sin(track.yaw[a, t0])
                        pyaw[j] = track.yaw[a, t0]
                    obstacles.place(px, py, pyaw)
            if k == cur + 1:
                for vid in held:
                    try:
                        ls.vehicle.setSpeed(vid, -1.0)
                    except Exception:
                        pass
            departed, arrived = sess.step()
            if obstacles is not None and later.intersection(departed):
                obstacles.retire(later.intersection(departed))
            # an agent leaving SUMO (its route ends) goes on at constant velocity: an obstacle
            left = [col[vid] for vid in arrived if vid in col and vid not in bundle.parked]
            if obstacles is not None and k > cur + 1 and left:
                t0 = k - cur - 2  # column of its last state in SUMO
                left = [a for a in left if np.isfinite(track.x[a, t0]) and a not in gone]
                if left:
                    gone.update({a: t0 for a in left})
                    obstacles.add([str(int(ids[a])) for a in left], length[left], width[left])
                    obs = np.r_[obs, np.array(left, np.int64)]
            for vid in departed:
                if not vid.startswith(OBSTACLE_PREFIX):
                    f = float(np.clip(rng.normal(1.0, SPEED_FACTOR_SD), 0.8, 1.2))
                    ls.vehicle.setSpeedFactor(vid, f)
            if k > cur:
                v = sess.vehicles()
                _continue_routes(ls, v, ends, bundle.parked, points)
                t = k - cur - 1
                sel = [(i, col[vid]) for i, vid in enumerate(v.ids)
                       if vid in col and vid not in bundle.parked]
                if sel:
                    i, a = (np.array(s) for s in zip(*sel))
                    track.x[a, t], track.y[a, t] = v.x[i], v.y[i]
                    track.yaw[a, t], track.speed[a, t] = v.yaw[i], v.speed[i]
    return fill_constant_velocity(scene, ids, track)


def _policy_rollout(scene: Scene, bundle_dir: Path, policy: Policy, seed: int,
                    counts: dict[str, int] | None = None) -> tuple[np.ndarray, ...]:
    """One rollout of ``policy`` driving every route vehicle through SumoDrivingEnv (with the
    policy's ``observation`` config when it has one, e.g. a SAC policy's route command).

    :param counts: the env's ``action_counts`` (missing / unknown / non-finite / clipped
        actions) are added to it."""
    from magail_sumo.env import EnvConfig, SumoDrivingEnv
    from magail_sumo.sim import dynamics

    ids = sim_agent_ids(scene)
    col = {str(int(i)): k for k, i in enumerate(ids)}
    cur = scene.current_time_index
    extra = {"observation": policy.observation} if hasattr(policy, "observation") else {}
    env = SumoDrivingEnv(scene, bundle_dir, EnvConfig(
        controlled="all", start_step=cur, max_steps=N_STEPS, terminate_on=(), **extra))
    track = _Track.empty(len(ids))
    try:
        obs, _ = env.reset(seed=seed)
        begin = getattr(policy, "begin", None)
        if callable(begin):  # optional extension (see Policy)
            begin(scene, env)
        while env.agents and env.t < cur + N_STEPS:
            st = env.agent_states()
            actions = policy.act(obs)
            none = (np.nan,) * ACTION_SIZE
            raw = np.stack([np.asarray(actions.get(n, none), np.float64).reshape(ACTION_SIZE)
                            for n in st.names])
            clean = np.clip(np.nan_to_num(raw, nan=0.0, posinf=0.0, neginf=0.0), -1.0, 1.0)
            accel, steer = dynamics.denormalise(clean, env.config.limits)
            nxt = dynamics.step(st.state, accel, steer, st.wheelbase, env.dt, env.config.limits)
            t = env.t - cur  # column of log step env.t + 1
            obs, *_ = env.step(actions)
            if 0 <= t < N_STEPS:
                sel = [(i, col[n]) for i, n in enumerate(st.names) if n in col]
                if sel:
                    i, a = (np.array(s) for s in zip(*sel))
                    track.x[a, t], track.y[a, t] = nxt.x[i], nxt.y[i]
                    track.yaw[a, t], track.speed[a, t] = nxt.yaw[i], nxt.speed[i]
        if counts is not None:
            for k, v in env.action_counts.items():
                counts[k] = counts.get(k, 0) + v
    finally:
        env.close()
    return fill_constant_velocity(scene, ids, track)


# ------------------------------------------------------------------------------- one method
def simulate(scene: Scene, method: str, rollouts: Iterable[int], seed: int = 0,
             bundle_dir: str | Path | None = None,
             action_counts: dict[str, int] | None = None,
             deterministic: bool = False) -> ScenarioRollouts:
    """Rollouts ``rollouts`` (indices) of one method on one scene, in this process.

    SUMO methods run one simulation after another here; callers batch them in fresh worker
    processes (:func:`run_batches`). Rollout ``r`` builds its policy with
    ``make_policy(method, rollout_seed(seed, r), deterministic)``.

    :param action_counts: a policy's fixed-up actions (the env's ``action_counts``: missing,
        unknown, non-finite, clipped) are added to it; they are also logged once.
    """
    ids = sim_agent_ids(scene)
    idx = list(rollouts)
    if method == "logreplay":
        from magail_sumo.evaluation.realism import log_replay

        ro = log_replay(scene, len(idx), N_STEPS)
        return ro
    xs, ys, yaws = [], [], []
    counts: dict[str, int] = {}
    for r in idx:
        s = rollout_seed(seed, r)
        if method == "constvel":
            x, y, yaw = constant_velocity(scene, ids)
        elif bundle_dir is None:
            raise EvaluationError(f"scenario {printable(scene.scenario_id)}: method {method} "
                                  "needs a converted SUMO bundle")
        elif method == "sumo":
            x, y, yaw = _sumo_rollout(scene, Path(bundle_dir), s)
        else:
            x, y, yaw = _policy_rollout(scene, Path(bundle_dir),
                                        make_policy(method, s, deterministic), s, counts)
        xs.append(x)
        ys.append(y)
        yaws.append(yaw)
    from magail_sumo.env.actions import action_summary

    fixed = action_summary(counts)
    if fixed:  # once per batch, in the run log
        log(f"warning: scenario {printable(scene.scenario_id)}: method {method} rollout(s) "
            f"{_span(tuple(idx))}: {fixed}")
    if action_counts is not None:
        for k, v in counts.items():
            action_counts[k] = action_counts.get(k, 0) + int(v)
    return _as_rollouts(scene, ids, xs, ys, yaws)


@dataclass(frozen=True)
class Batch:
    """Work for one worker process: some rollouts of one method on one scene.

    :param spec: method name or policy spec (see :func:`make_policy`).
    :param deterministic: a checkpoint policy acts deterministically (see :func:`make_policy`).
    """

    scene_file: str
    scenario_id: str
    bundle_dir: str
    spec: str
    rollouts: tuple[int, ...]
    seed: int
    deterministic: bool = False


def _load(scene_file: str, scenario_id: str) -> Scene:
    from converters import iter_scenes

    for scene in iter_scenes(scene_file):
        if scene.scenario_id == scenario_id:
            return scene
    raise EvaluationError(f"{scene_file}: scenario {printable(scenario_id)} not found")


def run_batch(batch: Batch) -> tuple[Batch, ScenarioRollouts, dict[str, int]]:
    """Worker entry point (module level, picklable): the batch, its rollouts and the policy's
    fixed-up action counts."""
    scene = _load(batch.scene_file, batch.scenario_id)
    counts: dict[str, int] = {}
    ro = simulate(scene, batch.spec, batch.rollouts, batch.seed, batch.bundle_dir, counts,
                  batch.deterministic)
    return batch, ro, counts


def needs_worker(spec: str) -> bool:
    return spec not in ("logreplay", "constvel")


#: seconds one worker job (a batch of rollouts of one method on one scene) may run by default
DEFAULT_TIMEOUT_S = 1800.0


def run_batches(batches: list[Batch], workers: int, timeout_s: float | None = DEFAULT_TIMEOUT_S
                ) -> Iterator[tuple[Batch, ScenarioRollouts | None, str | None, dict[str, int]]]:
    """Run batches, each in a fresh ``spawn`` process; yields (batch, rollouts, error line,
    fixed-up action counts).

    A batch whose worker fails (crashes, dies, raises anything but a
    :class:`~magail_sumo.errors.MagailSumoError`) is retried once rollout by rollout (each in
    its own process). A batch running longer than ``timeout_s`` seconds is killed and reported,
    not retried. No wait is unbounded (:func:`magail_sumo.workers.run_jobs`).
    """
    from magail_sumo.workers import run_jobs

    if not batches:
        return
    retry: list[Batch] = []
    for res in run_jobs(run_batch, batches, workers=max(1, workers), timeout_s=timeout_s):
        b = res.job
        what = f"scenario {b.scenario_id}: method {b.spec}"
        if res.ok:
            batch, ro, counts = res.value
            yield batch, ro, None, counts
        elif res.kind == "error" and res.expected:
            yield b, None, res.reason, {}
        elif res.kind == "timeout":
            yield b, None, (f"{what} rollout(s) {_span(b.rollouts)}: worker {res.reason} "
                            "(--timeout-s)"), {}
        elif len(b.rollouts) > 1:  # worker crash (libsumo) or bug: retry singly
            retry += [replace(b, rollouts=(r,)) for r in b.rollouts]
        else:
            yield b, None, f"{what} rollout {b.rollouts[0]} failed: {res.reason}", {}
    if retry:
        yield from run_batches(retry, workers, timeout_s)


def _span(rollouts: tuple[int, ...]) -> str:
    return str(rollouts[0]) if len(rollouts) == 1 else f"{rollouts[0]}-{rollouts[-1]}"


def merge(parts: list[ScenarioRollouts]) -> ScenarioRollouts:
    """Concatenate rollout batches of one scene (same agents) along the rollout axis."""
    first = parts[0]
    cat = lambda n: np.concatenate([getattr(p, n) for p in parts])  # noqa: E731
    return ScenarioRollouts(first.scenario_id, first.object_id, cat("x"), cat("y"), cat("z"),
                            cat("heading"))


# ---------------------------------------------------------------------------------- Parquet
def to_frame(scene: Scene, ro: ScenarioRollouts, method: str):
    """Long table (pandas) of the rollouts with the recorded history: one row per rollout,
    object and log step ``0..current + T``; ``valid`` is the log's validity for history steps
    (and for ``logreplay``), else True."""
    import pandas as pd

    tr = scene.tracks
    cur = scene.current_time_index
    R, A, T = ro.shape
    rows = np.array([int(np.flatnonzero(tr.id == i)[0]) for i in ro.object_id])
    hist = slice(0, cur + 1)

    def full(log: np.ndarray, sim: np.ndarray) -> np.ndarray:
        h = np.broadcast_to(log[rows, hist].astype(np.float32)[None], (R, A, cur + 1))
        return np.concatenate([h, sim.astype(np.float32)], axis=2)

    x, y, z, hd = (full(getattr(tr, n), getattr(ro, m)) for n, m in
                   (("x", "x"), ("y", "y"), ("z", "z"), ("heading", "heading")))
    fut_valid = (tr.valid[rows, cur + 1:cur + 1 + T] if method == "logreplay"
                 else np.ones((A, T), bool))
    valid = np.broadcast_to(np.concatenate([tr.valid[rows, hist], fut_valid], 1)[None],
                            x.shape)
    r_i, a_i, t_i = np.meshgrid(np.arange(R), np.arange(A), np.arange(cur + 1 + T),
                                indexing="ij")
    return pd.DataFrame({
        "scenario_id": pd.Categorical([ro.scenario_id] * x.size),
        "method": pd.Categorical([method] * x.size),
        "rollout": r_i.ravel().astype(np.int32),
        "object_id": ro.object_id[a_i.ravel()].astype(np.int64),
        "step": t_i.ravel().astype(np.int32),
        "x": x.ravel(), "y": y.ravel(), "z": z.ravel(), "heading": hd.ravel(),
        "valid": valid.ravel(),
    })


def rollouts_path(out: str | Path, method: str, scenario_id: str) -> Path:
    """``out/rollouts/<method>/<scenario_id>.parquet``, both names through
    :func:`~magail_sumo.outputs.safe_name` (unchanged for the built-in methods and real WOMD
    ids), refused (:class:`~magail_sumo.outputs.OutputError`) unless inside ``out``."""
    return inside(out, "rollouts", safe_name(method), f"{safe_name(scenario_id)}.parquet")


def write_rollout_fcd(out: str | Path, scene: Scene, ro: ScenarioRollouts, method: str,
                      bundle: Path, rollouts: int) -> list[Path]:
    """SUMO FCD of the first ``rollouts`` rollouts, each with a ``.sumocfg`` replaying it on the
    scene's converted network in ``sumo-gui`` (:mod:`magail_sumo.sim.fcd`):
    ``out/fcd/<method>/<scenario_id>/rollout<r>.fcd.xml`` (names through
    :func:`~magail_sumo.outputs.safe_name`). The recorded history (log steps ``0..current``,
    where valid) is followed by the simulated steps; times are ``step * 0.1`` s. Returns the
    ``.sumocfg`` paths."""
    from magail_sumo.sim.fcd import SHAPES, FcdRecorder, write_replay

    tr = scene.tracks
    cur = scene.current_time_index
    r_n, a_n, t_n = ro.shape
    row_of = {int(i): k for k, i in enumerate(tr.id.tolist())}
    rows = np.array([row_of[int(i)] for i in ro.object_id], np.int64)
    hist = slice(0, cur + 1)
    valid = np.concatenate([tr.valid[rows, hist], np.ones((a_n, t_n), bool)], axis=1)
    size = {}
    for name in ("length", "width"):
        v = np.where(tr.valid[rows], getattr(tr, name)[rows], np.nan)
        size[name] = np.nan_to_num(np.nanmedian(v, axis=1), nan=1.0)  # valid at current
    shape = [SHAPES.get(int(t), "passenger") for t in tr.type[rows]]
    name = safe_name(scene.scenario_id)
    net = bundle / f"{name}.net.xml"
    tll = bundle / f"{name}.tll.xml"
    times = np.arange(cur + 1 + t_n) * DT
    written = []
    for r in range(min(rollouts, r_n)):
        rec = FcdRecorder(DT)
        x, y, hd = (np.concatenate([getattr(tr, n)[rows, hist].astype(np.float64),
                                    getattr(ro, m)[r].astype(np.float64)], axis=1)
                    for n, m in (("x", "x"), ("y", "y"), ("heading", "heading")))
        rec.add_tracks(times, ro.object_id, x, y, hd, valid, size["length"], size["width"],
                       "agent", shape)
        path = inside(out, "fcd", safe_name(method), name, f"rollout{r:03d}.fcd.xml")
        written.append(write_replay(rec, path, net, [tll] if tll.is_file() else []).sumocfg)
    return written


def write_parquet(path: str | Path, frame) -> None:
    """Write ``frame`` to ``path`` atomically (a temporary file renamed into place)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        frame.to_parquet(tmp, index=False)


def read_rollouts(path: str | Path, scene: Scene) -> ScenarioRollouts:
    """Simulated steps (after the scene's current step) of a rollouts Parquet file.

    :raises EvaluationError: unreadable file, missing columns, another scene, or a ragged
        table (agents without every rollout and step), naming the file / scene / agent.
    """
    import pandas as pd

    path = Path(path)
    try:
        df = pd.read_parquet(path)
    except Exception as exc:
        raise EvaluationError(f"{path}: unreadable Parquet ({type(exc).__name__})") from None
    missing = [c for c in COLUMNS if c not in df.columns]
    if missing:
        raise EvaluationError(f"{path}: missing column(s) {', '.join(missing)}")
    sids = df["scenario_id"].astype(str).unique()
    sid = scene.scenario_id
    if len(sids) != 1 or sids[0] != sid:
        raise EvaluationError(f"{path}: holds scenario(s) {', '.join(map(str, sids[:3]))}, "
                              f"expected {sid}")
    fut = df[df["step"] > scene.current_time_index].sort_values(["rollout", "object_id", "step"])
    ids = np.sort(fut["object_id"].unique())
    R, A = fut["rollout"].nunique(), len(ids)
    if A == 0:
        raise EvaluationError(f"scenario {sid}: {path.name} has no simulated steps")
    counts = fut.groupby("object_id").size()
    T, rem = divmod(len(fut), R * A)
    bad = counts[counts != counts.max()]
    if rem or len(bad):
        oid = int(bad.index[0]) if len(bad) else int(ids[0])
        raise EvaluationError(f"scenario {sid}: agent {oid} has {int(counts.get(oid, 0))} "
                              f"rows in {path.name}, others {int(counts.max())} "
                              "(every agent needs every rollout and step)")
    arr = {c: fut[c].to_numpy(np.float32).reshape(R, A, T) for c in ("x", "y", "z", "heading")}
    return ScenarioRollouts(sid, ids.astype(np.int64), arr["x"], arr["y"], arr["z"],
                            arr["heading"])


# --------------------------------------------------------------------------------- manifest
def versions() -> dict[str, str]:
    from magail_sumo.config import environment_versions

    out = dict(environment_versions())
    for pkg in ("pandas", "pyarrow", "libsumo", "sumolib"):
        try:
            from importlib import metadata

            out[pkg] = metadata.version(pkg)
        except Exception:
            pass
    return out


def previous_manifest(out: Path) -> dict:
    """``out/manifest.json`` as a dict to merge into ({} when absent, unreadable or not an
    object; :func:`read_manifest` is the strict reader)."""
    path = out / "manifest.json"
    try:
        man = json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, ValueError):
        man = {}
    return man if isinstance(man, dict) else {}


def write_manifest(out: Path, manifest: dict) -> None:
    """Merge ``manifest`` into ``out/manifest.json`` (methods and scenes accumulate; an
    unreadable old manifest is replaced); written atomically."""
    path = out / "manifest.json"
    old = previous_manifest(out)
    if old and (old.get("rollouts"), old.get("seed")) != (manifest["rollouts"], manifest["seed"]):
        # another run setting: start afresh (city results, evaluation.city, do not depend on it)
        old = {"city": old["city"]} if "city" in old else {}
    scenes = {s["scenario_id"]: s for s in old.get("scenes", [])}
    scenes.update({s["scenario_id"]: s for s in manifest["scenes"]})
    methods = list(dict.fromkeys(list(old.get("methods", [])) + list(manifest["methods"])))
    fixes = {(f["scenario_id"], f["method"]): f for f in old.get("action_fixes", [])
             if isinstance(f, dict) and f.get("method") not in manifest["methods"]}
    fixes.update({(f["scenario_id"], f["method"]): f for f in manifest.get("action_fixes", [])})
    merged = {**old, **manifest, "scenes": list(scenes.values()), "methods": methods,
              "action_fixes": list(fixes.values())}
    write_text(path, json.dumps(merged, indent=2) + "\n")


def read_manifest(out: str | Path) -> dict:
    path = Path(out) / "manifest.json"
    if not path.is_file():
        raise EvaluationError(f"{path}: no manifest (run magail-sumo evaluate --out {out})")
    try:
        return json.loads(path.read_text())
    except ValueError as exc:
        raise EvaluationError(f"{path}: unreadable manifest ({exc})") from None


def chunks(n: int, size: int) -> list[tuple[int, ...]]:
    return [tuple(range(i, min(i + size, n))) for i in range(0, n, size)]


def batch_size(n_rollouts: int, workers: int) -> int:
    return max(1, min(8, math.ceil(n_rollouts / max(1, workers))))


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


__all__ = ["BASELINES", "Batch", "EvaluationError", "POLICY_LOADERS", "Policy",
           "RandomPolicy", "constant_velocity", "make_policy", "method_name", "read_rollouts",
           "rollout_seed", "run_batches", "simulate", "to_frame"]


# ------------------------------------------------------------------------------- evaluation
@dataclass
class EvaluationResult:
    """What :func:`evaluate` wrote: (scenario, method) pairs done, and one-line errors."""

    done: list[tuple[str, str]]
    errors: list[str]


def _bundle(scene: Scene, networks: Path | None, out: Path,
            timeout_s: float | None = DEFAULT_TIMEOUT_S) -> Path:
    """A converted bundle of ``scene``: reused from ``networks`` when complete, else converted
    into ``out/networks`` (:func:`converters.sumo.bundle.ensure_bundle`)."""
    from converters.sumo.bundle import ensure_bundle

    return ensure_bundle(scene, out / "networks", time_budget_s=timeout_s,
                         search=[networks] if networks else [], claim=True)


def evaluate(scene_files: list[str], policy: str, out: str | Path, *, n_rollouts: int = 32,
             baselines: Iterable[str] = BASELINES, seed: int = 0, workers: int = 2,
             networks: str | Path | None = None, submission: str | Path | None = None,
             timeout_s: float | None = DEFAULT_TIMEOUT_S, fcd_rollouts: int = 0,
             name: str | None = None, deterministic: bool = False) -> EvaluationResult:
    """Rollouts of ``policy`` and ``baselines`` on every scene, written as Parquet under
    ``out/rollouts/<method>/<scenario_id>.parquet`` plus ``out/manifest.json``; with
    ``fcd_rollouts`` > 0 the first that many rollouts of every scene and method also as SUMO
    FCD with a ``sumo-gui`` replay config (:func:`write_rollout_fcd`).

    ``out`` must be new, empty or written by magail_sumo
    (:func:`~magail_sumo.outputs.claim_output_dir`, else
    :class:`~magail_sumo.outputs.OutputError`); file names come from :func:`rollouts_path`, the
    manifest and the Parquet ``scenario_id`` column keep the original ids, and every file is
    written atomically. Bad scenes, failed conversions and failed rollouts (any exception, a
    worker that dies, or one running past ``timeout_s`` seconds: killed) are reported (stderr,
    one line each) and the rest goes on.

    :param name: the policy's method name (default :func:`method_name` of the spec); rollouts,
        the manifest and the report use it.
    :param deterministic: a checkpoint policy acts with the tanh of its Gaussian mean (every
        rollout alike) instead of sampling its actions with the rollout seed (the default);
        recorded in the manifest.
    :raises EvaluationError: an unknown baseline, an unusable policy spec, bad counts or a
        name that is empty, not printable or another method's.
    """
    from converters.scene_files import iter_scene_records
    from magail_sumo.evaluation.submission import validate_rollouts, write_submission

    out = Path(out)
    if n_rollouts < 1:
        raise EvaluationError(f"--rollouts must be >= 1, got {n_rollouts}")
    if fcd_rollouts < 0:
        raise EvaluationError(f"--fcd-rollouts must be >= 0, got {fcd_rollouts}")
    bad = [b for b in baselines if b not in BASELINES]
    if bad:
        raise EvaluationError(f"unknown baseline {bad[0]} (known: {', '.join(BASELINES)})")
    if policy not in BASELINES:
        make_policy(policy, seed, deterministic)  # fail early on an unusable spec
    specs = list(dict.fromkeys([policy, *baselines]))
    names = {s: method_name(s) for s in specs}
    if name is not None:
        if not name.strip() or not name.isprintable() or len(name) > 100:
            raise EvaluationError(f"--name {printable(name)!r}: must be a non-empty printable "
                                  "name of at most 100 characters")
        if name in BASELINES + BUILTIN_POLICIES and name != policy:
            raise EvaluationError(f"--name {name!r}: is a built-in method's name")
        names[policy] = name
    method_files = NameRegistry()
    for s in specs:
        method_files.name(names[s])
    claim_output_dir(out, "evaluate", ["manifest.json", "rollouts", "networks"]
                     + (["fcd"] if fcd_rollouts else []))
    scene_names = NameRegistry()  # rollouts file names of the scenes
    errors: list[str] = []

    def error(msg: str) -> None:
        msg = msg if msg.isprintable() else printable(msg, 2000)  # one line, whatever the ids
        errors.append(msg)
        log(f"error: {msg}")

    scenes: dict[str, tuple[str, Scene, Path | None]] = {}
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
                    scene_names.name(sc.scenario_id)
                except OutputError as exc:
                    error(f"{f}: {exc}; scenario {shown} skipped")
                    continue
                scenes[sc.scenario_id] = (str(Path(f).resolve()), sc, None)
        except MagailSumoError as exc:
            error(" ".join(str(exc).split()))
        except Exception as exc:  # noqa: BLE001 - one file's failure, the batch goes on
            error(f"{f}: {type(exc).__name__}: {_line(exc)}")
    need_sumo = any(needs_worker(s) for s in specs) or fcd_rollouts > 0  # FCD: the network
    for sid, (f, sc, _) in list(scenes.items()):
        if need_sumo:
            try:
                scenes[sid] = (f, sc, _bundle(sc, Path(networks) if networks else None, out,
                                              timeout_s))
            except MagailSumoError as exc:
                error(" ".join(str(exc).split()))
                del scenes[sid]
            except Exception as exc:  # noqa: BLE001 - one scene's failure, the batch goes on
                error(f"scenario {sid}: {type(exc).__name__}: {_line(exc)}")
                del scenes[sid]
    results: dict[tuple[str, str], list[tuple[int, ScenarioRollouts]]] = {}
    batches = []
    size = batch_size(n_rollouts, workers)
    for sid, (f, sc, bdir) in scenes.items():
        for s in specs:
            if needs_worker(s):
                batches += [Batch(f, sid, str(bdir), s, c, seed, deterministic)
                            for c in chunks(n_rollouts, size)]
            else:
                try:
                    results[(sid, s)] = [(0, simulate(sc, s, range(n_rollouts), seed))]
                except Exception as exc:  # noqa: BLE001 - one scene's failure
                    error(f"scenario {sid}: method {s}: {type(exc).__name__}: {_line(exc)}")
    failed: set[tuple[str, str]] = set()
    fixes: dict[tuple[str, str], dict[str, int]] = {}  # a policy's fixed-up actions
    for b, ro, err, counts in run_batches(batches, workers, timeout_s):
        if err is not None:
            error(err)
            failed.add((b.scenario_id, b.spec))
        else:
            results.setdefault((b.scenario_id, b.spec), []).append((b.rollouts[0], ro))
            tally = fixes.setdefault((b.scenario_id, b.spec), {})
            for k, v in counts.items():
                tally[k] = tally.get(k, 0) + v
    done: list[tuple[str, str]] = []
    policy_ros: list[ScenarioRollouts] = []
    for sid, (f, sc, bdir) in scenes.items():
        for s in specs:
            if (sid, s) in failed or (sid, s) not in results:
                continue
            try:
                ro = merge([r for _, r in sorted(results[(sid, s)], key=lambda p: p[0])])
                validate_rollouts(ro, sc, n_rollouts, N_STEPS)
            except MagailSumoError as exc:
                error(f"method {names[s]}: {' '.join(str(exc).split())}")
                continue
            except Exception as exc:  # noqa: BLE001 - one scene's failure
                error(f"scenario {printable(sid)}: method {names[s]}: {type(exc).__name__}: "
                      f"{_line(exc)}")
                continue
            write_parquet(rollouts_path(out, names[s], sid), to_frame(sc, ro, names[s]))
            if fcd_rollouts and bdir is not None:
                write_rollout_fcd(out, sc, ro, names[s], Path(bdir), fcd_rollouts)
            done.append((sid, names[s]))
            if s == policy:
                policy_ros.append(ro)
    manifest = {
        "scenes": [{"scenario_id": sid, "file": f, "bundle": str(b) if b else None,
                    "num_steps": sc.num_steps, "current_time_index": sc.current_time_index,
                    "agents": int(len(sim_agent_ids(sc)))}
                   for sid, (f, sc, b) in scenes.items()],
        "methods": [names[s] for s in specs], "policy": names[policy], "policy_spec": policy,
        "baselines": [names[b] for b in baselines], "rollouts": n_rollouts, "steps": N_STEPS,
        "seed": seed, "deterministic": bool(deterministic), "versions": versions(),
        # actions the policy did not give (agents coasted), gave for unknown agents, or gave
        # non-finite / outside [-1, 1] (fixed up by the env), per scene and method
        "action_fixes": [{"scenario_id": sid, "method": names[s], **c}
                         for (sid, s), c in fixes.items() if (sid, names[s]) in done
                         and any(c.get(k) for k in ("missing", "unknown", "nonfinite",
                                                    "clipped"))],
    }
    out.mkdir(parents=True, exist_ok=True)
    write_manifest(out, manifest)
    if submission is not None and policy_ros:
        write_submission(submission, policy_ros, method_name=names[policy],
                         description=f"magail_sumo evaluate --policy {policy}")
    return EvaluationResult(done, errors)
