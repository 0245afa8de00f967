"""Closed-loop rollouts of recorded scenes under the WOSAC protocol, stored as Parquet.

Protocol: log steps ``0..current_time_index`` are the recorded history; the next 80 steps
(8 s at 0.1 s) are simulated for every object valid at ``current_time_index`` (the official
sim-agent set). Methods:

* ``logreplay``: the recorded future (stored states, invalid ones included).
* ``constvel``: constant velocity from the recorded state at the current step (heading held).
* ``sumo``: SUMO's default car-following (Krauss) drives the converted routes from every route
  vehicle's recorded pose and speed at the current step, each with a seeded speed factor; every
  other sim agent moves at constant velocity and is an obstacle SUMO's drivers brake for
  (:mod:`magail_sumo.agents.sumo_baseline` has the details).
* a policy (``random``, or a checkpoint / ``module:factory`` spec, see
  :func:`magail_sumo.policies.make_policy`): drives every route vehicle and cyclist through
  :class:`~magail_sumo.env.SumoDrivingEnv` (bicycle model, SUMO co-simulation, no event
  terminates an agent; :func:`magail_sumo.agents.rollout`), built with the policy's
  ``observation``, ``action_layout`` and gap ``guard`` when it names them. Each rollout builds
  its policy with the rollout seed; a training checkpoint samples its actions from that seed
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

import json
import math
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from converters.scene_files import find_scene, iter_scene_records
from converters.sumo.bundle import BundleLayout
from converters.sumo.scenario import ensure_bundle
from magail_sumo.agents import Policy, PolicyError, RandomPolicy, env_settings, rollout
from magail_sumo.agents import constant_velocity as _cv
from magail_sumo.agents.constant_velocity import Track as _Track
from magail_sumo.agents.constant_velocity import current_state as _current_state
from magail_sumo.agents.constant_velocity import fill_constant_velocity
from magail_sumo.agents.sumo_baseline import sumo_rollout
from magail_sumo.config import environment_versions
from magail_sumo.env import EnvConfig, SumoDrivingEnv
from magail_sumo.env.actions import action_summary
from magail_sumo.errors import MagailSumoError
from magail_sumo.evaluation.realism import log_replay
from magail_sumo.evaluation.submission import (ScenarioRollouts, sim_agent_ids, validate_rollouts,
                                               write_submission)
from magail_sumo.outputs import (NameRegistry, OutputError, atomic_path, claim_output_dir, inside,
                                 one_line, printable, safe_name, write_text)
from magail_sumo.policies import (BASELINES, BUILTIN_POLICIES, POLICY_LOADERS, make_policy,
                                  method_name)
from magail_sumo.scene import Scene
from magail_sumo.scene.types import STEP_LENGTH
from magail_sumo.sim.dynamics import wrap_angle
from magail_sumo.sim.fcd import FcdRecorder, SHAPES, write_replay
from magail_sumo.workers import run_jobs

N_STEPS = 80  #: simulated steps per rollout (8 s)
DT = STEP_LENGTH  #: s per step
SUMO_METHODS = ("sumo",)  #: baselines that need SUMO (worker processes)
COLUMNS = ("scenario_id", "method", "rollout", "object_id", "step", "x", "y", "z", "heading",
           "valid")


class EvaluationError(MagailSumoError):
    """A rollout or evaluation input cannot be used (one line naming the scene / agent)."""


def _line(exc: BaseException) -> str:
    return one_line(exc)


def rollout_seed(seed: int, rollout: int) -> int:
    """Seed of one rollout (SUMO and numpy), from the run seed; < 2**31."""
    return int(np.random.SeedSequence([seed, rollout]).generate_state(1)[0] % (2 ** 31 - 1))


# ------------------------------------------------------------------------- trajectory models
def constant_velocity(scene: Scene, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, yaw) (A, :data:`N_STEPS`): recorded state at the current step moved at its
    velocity (:func:`magail_sumo.agents.constant_velocity.constant_velocity`)."""
    return _cv.constant_velocity(scene, ids, N_STEPS)


def _as_rollouts(scene: Scene, ids: np.ndarray, xs: list, ys: list, yaws: list
                 ) -> ScenarioRollouts:
    _, _, _, z0, _, _, _ = _current_state(scene, ids)
    x, y, yaw = (np.stack(v).astype(np.float32) for v in (xs, ys, yaws))
    yaw = wrap_angle(yaw).astype(np.float32)
    z = np.broadcast_to(z0.astype(np.float32)[None, :, None], x.shape).copy()
    return ScenarioRollouts(scene.scenario_id, ids.astype(np.int64), x, y, z, yaw)


# ---------------------------------------------------------------------------- policy rollouts
def _policy_rollout(scene: Scene, bundle_dir: Path, policy: Policy, seed: int,
                    counts: dict[str, int] | None = None) -> tuple[np.ndarray, ...]:
    """One rollout of ``policy`` driving every route vehicle through SumoDrivingEnv (with the
    policy's ``observation`` config, ``action_layout`` and ``guard`` when it has them, e.g. a
    SAC policy's route command), by :func:`magail_sumo.agents.rollout`. Each agent's simulated
    state at a step is the one the env reports after it (``infos[agent]["state"]``).

    :param counts: the env's ``action_counts`` (missing / unknown / non-finite / clipped
        actions) are added to it."""
    ids = sim_agent_ids(scene)
    col = {str(int(i)): k for k, i in enumerate(ids)}
    cur = scene.current_time_index
    env = SumoDrivingEnv(scene, bundle_dir, EnvConfig(
        controlled="all", start_step=cur, max_steps=N_STEPS, terminate_on=(),
        end_of_life=False, **env_settings(policy)))
    track = _Track.empty(len(ids), N_STEPS)

    def keep(step) -> None:
        t = step.t - cur  # column of log step step.t + 1
        if not 0 <= t < N_STEPS:
            return
        sel = [(col[n], step.infos[n]["state"]) for n in step.agents if n in col]
        if sel:
            a = np.array([s[0] for s in sel])
            state = np.array([s[1] for s in sel], np.float64)  # (n, 4): x, y, yaw, speed
            track.x[a, t], track.y[a, t] = state[:, 0], state[:, 1]
            track.yaw[a, t], track.speed[a, t] = state[:, 2], state[:, 3]

    try:
        rollout(env, policy, keep, seed=seed, max_steps=N_STEPS, scene=scene)
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
             deterministic: bool = False, noise_scale: float | None = None
             ) -> ScenarioRollouts:
    """Rollouts ``rollouts`` (indices) of one method on one scene, in this process.

    SUMO methods run one simulation after another here; callers batch them in fresh worker
    processes (:func:`run_batches`). Rollout ``r`` builds its policy with
    ``make_policy(method, rollout_seed(seed, r), deterministic, noise_scale)``.

    :param action_counts: a policy's fixed-up actions (the env's ``action_counts``: missing,
        unknown, non-finite, clipped) are added to it; they are also logged once.
    """
    ids = sim_agent_ids(scene)
    idx = list(rollouts)
    if method == "logreplay":
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
            x, y, yaw = sumo_rollout(scene, Path(bundle_dir), s, ids, N_STEPS)
        else:
            x, y, yaw = _policy_rollout(scene, Path(bundle_dir),
                                        make_policy(method, s, deterministic, noise_scale),
                                        s, counts)
        xs.append(x)
        ys.append(y)
        yaws.append(yaw)

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
    :param noise_scale: its sampling noise's scale (None: the policy's own; see
        :func:`make_policy`).
    """

    scene_file: str
    scenario_id: str
    bundle_dir: str
    spec: str
    rollouts: tuple[int, ...]
    seed: int
    deterministic: bool = False
    noise_scale: float | None = None


def _load(scene_file: str, scenario_id: str) -> Scene:
    return find_scene(scene_file, scenario_id)


def run_batch(batch: Batch) -> tuple[Batch, ScenarioRollouts, dict[str, int]]:
    """Worker entry point (module level, picklable): the batch, its rollouts and the policy's
    fixed-up action counts."""
    scene = _load(batch.scene_file, batch.scenario_id)
    counts: dict[str, int] = {}
    ro = simulate(scene, batch.spec, batch.rollouts, batch.seed, batch.bundle_dir, counts,
                  batch.deterministic, batch.noise_scale)
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

    files = BundleLayout.of(bundle, scene.scenario_id)
    name, net, tll = files.name, files.net, files.signals
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


__all__ = ["BASELINES", "Batch", "EvaluationError", "POLICY_LOADERS", "Policy", "PolicyError",
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
    into ``out/networks`` (:func:`converters.sumo.scenario.ensure_bundle`)."""
    return ensure_bundle(scene, out / "networks", time_budget_s=timeout_s,
                         search=[networks] if networks else [], claim=True)


def evaluate(scene_files: list[str], policy: str, out: str | Path, *, n_rollouts: int = 32,
             baselines: Iterable[str] = BASELINES, seed: int = 0, workers: int = 2,
             networks: str | Path | None = None, submission: str | Path | None = None,
             timeout_s: float | None = DEFAULT_TIMEOUT_S, fcd_rollouts: int = 0,
             name: str | None = None, deterministic: bool = False,
             noise_scale: float | None = None) -> EvaluationResult:
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
    :param noise_scale: a sampling policy's noise scale (``tanh(mu + k·sigma·eps)``; None: the
        policy's own, 1 or a pretrained card's); the one used is recorded in the manifest.
    :raises EvaluationError: an unknown baseline, an unusable policy spec, bad counts or a
        name that is empty, not printable or another method's.
    """
    out = Path(out)
    if n_rollouts < 1:
        raise EvaluationError(f"--rollouts must be >= 1, got {n_rollouts}")
    if fcd_rollouts < 0:
        raise EvaluationError(f"--fcd-rollouts must be >= 0, got {fcd_rollouts}")
    bad = [b for b in baselines if b not in BASELINES]
    if bad:
        raise EvaluationError(f"unknown baseline {bad[0]} (known: {', '.join(BASELINES)})")
    scale = None  # the noise scale the policy samples with (manifest)
    if policy not in BASELINES:  # fail early on an unusable spec
        scale = getattr(make_policy(policy, seed, deterministic, noise_scale), "noise_scale",
                        None)
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
                batches += [Batch(f, sid, str(bdir), s, c, seed, deterministic, noise_scale)
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
        "seed": seed, "deterministic": bool(deterministic), "noise_scale": scale,
        "versions": versions(),
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
