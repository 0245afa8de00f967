"""Env throughput: a recorded scene and a city, every vehicle controlled.

Measures (one process, one core): agent-steps/s of the full env step (SUMO step + control +
sensors + observations + events); the floor: raw libsumo stepping of the same scenario with the
same vehicles moved each step; the share of env step time spent in sensors and observations.

* ``637f20cafde22ff8``: the bundled WOMD scene converted, every route vehicle controlled,
  driven by expert (inverse-dynamics) actions; floor: the vehicles moved to their recorded poses.
* ``ingolstadt21``: the InTAS Ingolstadt cut-out (data/sumo/ingolstadt21) warmed up by SUMO for
  ``--warmup`` s, then every vehicle present or departing controlled (several hundred), driven
  with zero actions (events reported, nobody terminated); floor: every vehicle moved to its own
  SUMO pose each step.

* ``windows``: training's episodes — random 80-step windows (start >= 10, the log before as
  history), every route vehicle controlled, expert actions — on the bundled scene and two 20 s
  ScenarioNet scenes (``data/scenarionet/``), timed whole (``reset`` included: SUMO's start and
  the history steps before the window), with the SUMO mirror (the default) and without
  (``EnvConfig.sumo_mirror=False``: the same episodes without SUMO). The two variants alternate
  ``--repeats`` times over the same seeded windows; rows give the median agent-steps/s of each
  and their ratio.
* ``guard_edge`` (only by name, not in ``all``): the same windows without the SUMO mirror, with
  and without the gap guard and the road-edge off-road rule (``EnvConfig.guard``,
  ``off_road_rule: road_edge``): what the two cost.
* ``batched`` (only by name): the batched core against one env per rollout, on the bundled
  scene in evaluation's setting (every route vehicle from the current step for 80 steps,
  nobody ends early, log background without the SUMO mirror, actions [0.1, 0]): W rollouts as
  W episodes of one ``SumoDrivingEnv`` (the PettingZoo dicts) against one episode of a
  ``BatchedSceneEnv`` with W worlds (the array API), alternating, for each W of
  ``--worlds`` (by default 61, about 1,000 and 10,000 agents at once); medians of
  ``--repeats``.
* ``worker`` (only by name): the scene worker's step as training runs it (``SlotWorker``:
  slots, packets; the womd14 recipe's episodes: random 80-step windows, collision and
  off-road end an agent, no SUMO mirror) on the window scenes, on the recorded env's array
  API against its dict API (the worker before it used the arrays), alternating; ``--steps``
  worker steps of seeded random actions each, medians of ``--repeats``.

* ``tiled`` (only by name): a scene worker playing the 10 train scenes of
  ``configs/splits/womd14.yaml`` (the recipe's episodes, as ``worker``) one scene per episode
  against all of them at once as one tiled env (``workers.scenes_per_env: 10``,
  ``magail_sumo.env.tile_pool``), alternating; ``--steps`` worker steps each, medians of
  ``--repeats``. Bundles from ``--networks`` (converted there on demand).

    python benchmarks/env_throughput.py [--json] [--episodes N] [--scenario NAME|all]
        [--repeats R] [--worlds W ...] [--networks DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from converters import load_scene  # noqa: E402
from converters.sumo.scenario import ConvertOptions, convert_scene  # noqa: E402
from magail_sumo.env import REPLAY_LIMITS, EnvConfig, SumoDrivingEnv, expert_actions  # noqa: E402
from magail_sumo.env.guard import GuardConfig  # noqa: E402
from magail_sumo.sim.session import SessionConfig, SumoSession  # noqa: E402
from magail_sumo.workers import run_one  # noqa: E402

SCENE = "637f20cafde22ff8"
CITY = "ingolstadt21"
WINDOWS = "windows"
#: the windows measure of the gap guard and the road-edge off-road rule (both on vs both off,
#: without the SUMO mirror)
GUARD_EDGE = "guard_edge"
#: the batched core against one env per rollout (only by name)
BATCHED = "batched"
#: the scene worker's array API against its dict API (only by name)
WORKER = "worker"
#: the tiled worker against the one-scene worker (only by name)
TILED = "tiled"
#: scenes of the ``windows`` measurement: the bundled TFRecord and two 20 s ScenarioNet scenes
WINDOW_SCENES = (ROOT / "data" / "womd" / f"{SCENE}.tfrecord",
                 ROOT / "data" / "scenarionet" / "b36a6d0bc9e525bc.pkl",
                 ROOT / "data" / "scenarionet" / "7b24d74b506c94ce.pkl")


def run_env(env: SumoDrivingEnv, episodes: int) -> tuple[float, int, float, int]:
    """(seconds in step(), agent-steps, seconds in sensors, peak agents)."""
    total, agent_steps, sensors, peak = 0.0, 0, 0.0, 0
    for ep in range(episodes):
        env.reset(seed=ep)
        while env.agents:
            acts = expert_actions(env)
            peak = max(peak, len(acts))
            s0 = env.sensor_time
            t0 = time.perf_counter()
            env.step(acts)
            total += time.perf_counter() - t0
            sensors += env.sensor_time - s0
            agent_steps += len(acts)
    return total, agent_steps, sensors, peak


def run_raw(cfg: Path, scene, ids: set[str], episodes: int) -> tuple[float, int]:
    """(seconds, steps) of SumoSession.step + move of the same vehicles to their log poses."""
    tr = scene.tracks
    row = {str(int(t)): k for k, t in enumerate(tr.id.tolist())}
    last = tr.valid.shape[1] - 1 - np.argmax(tr.valid[:, ::-1], axis=1)
    total, steps = 0.0, 0
    for _ in range(episodes):
        with SumoSession(cfg) as sim:
            present: list[str] = []
            for t in range(scene.num_steps - 1):
                t0 = time.perf_counter()
                dep, arr = sim.step()
                present = [v for v in present if v not in set(arr)] + [v for v in dep if v in ids]
                r = np.array([row[v] for v in present], np.int64)
                ok = tr.valid[r, t + 1] if r.size else np.zeros(0, bool)
                for i in np.flatnonzero(~ok & (last[r] <= t)):  # life over: leave, as in the env
                    sim.remove(present[i])
                present = [v for v, keep in zip(present, ok | (last[r] > t)) if keep]
                r = np.array([row[v] for v in present], np.int64)
                ok = tr.valid[r, t + 1] if r.size else np.zeros(0, bool)
                if ok.any():
                    rr = r[ok]
                    sim.move([present[i] for i in np.flatnonzero(ok)], tr.x[rr, t + 1],
                             tr.y[rr, t + 1], tr.heading[rr, t + 1].astype(float),
                             tr.length[rr, t + 1].astype(float))
                total += time.perf_counter() - t0
                steps += 1
    return total, steps


def run_city_raw(cfg: Path, state: str, steps: int) -> tuple[float, int, int]:
    """(seconds, steps, peak vehicles) of raw stepping with every vehicle moved to its own pose."""
    with SumoSession(cfg, config=SessionConfig(extra_args=("--load-state", state))) as sim:
        total, peak = 0.0, 0
        for _ in range(steps):
            t0 = time.perf_counter()
            v = sim.vehicles()
            sim.move(list(v.ids), v.x, v.y, v.yaw, v.length)
            sim.step()
            total += time.perf_counter() - t0
            peak = max(peak, len(v))
    return total, steps, peak


def _call(job: tuple):
    fn, args = job
    return fn(*args)


def _in_fresh_process(fn, *args):
    """``fn(*args)`` in a fresh worker process (:func:`magail_sumo.workers.run_one`)."""
    res = run_one(_call, (fn, args))
    if not res.ok:
        raise SystemExit(f"{fn.__name__}: {res.reason}")
    return res.value


def run_city(args) -> dict:
    from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv

    cfg = ROOT / "data" / "sumo" / CITY / f"{CITY}.sumocfg"
    env = SumoCityEnv(cfg, CityEnvConfig(warmup_s=args.warmup, max_steps=args.city_steps,
                                         terminate_on=()))
    secs = sensors = 0.0
    agent_steps, peak, steps = 0, 0, 0
    for ep in range(args.episodes + 1):  # the first episode warms numba and SUMO up
        env.reset(seed=ep)
        while env.agents:
            acts = {a: np.zeros(2, np.float32) for a in env.agents}
            s0, t0 = env.sensor_time, time.perf_counter()
            env.step(acts)
            if ep:
                secs += time.perf_counter() - t0
                sensors += env.sensor_time - s0
                agent_steps += len(acts)
                peak = max(peak, len(acts))
                steps += 1
    state = str(env.warm_state())
    raw_secs, raw_steps, raw_peak = _in_fresh_process(run_city_raw, cfg, state, args.city_steps)
    env.close()
    return {
        "scene": CITY,
        "agents": peak,
        "agent_steps_per_s": round(agent_steps / secs, 1),
        "raw_sumo_steps_per_s": round(raw_steps / raw_secs, 1),
        "sensor_share": round(sensors / secs, 3),
        "mean_live_agents": round(agent_steps / steps, 1),
        "env_steps_per_s": round(steps / secs, 1),
        "raw_vehicles_moved_peak": raw_peak,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object per scenario")
    ap.add_argument("--episodes", type=int, default=3)
    ap.add_argument("--scenario", default="all",
                    choices=[SCENE, CITY, WINDOWS, GUARD_EDGE, BATCHED, WORKER, TILED, "all"],
                    help=f"{WINDOWS}: with vs without the SUMO mirror; {GUARD_EDGE}: with vs "
                         "without the gap guard and the road-edge off-road rule (all: every "
                         f"one but {GUARD_EDGE})")
    ap.add_argument("--repeats", type=int, default=3, help="repeats of the windows measurement")
    ap.add_argument("--warmup", type=float, default=1200.0, help="city warm-up (s of SUMO time)")
    ap.add_argument("--city-steps", type=int, default=100, help="0.1-s steps per city episode")
    ap.add_argument("--steps", type=int, default=400, help=f"{WORKER}: worker steps per run")
    ap.add_argument("--worlds", type=int, nargs="+", default=[1, 16, 164],
                    help=f"{BATCHED}: world counts (the bundled scene has 61 agents per world)")
    ap.add_argument("--networks", type=Path, default=None,
                    help=f"{TILED}: bundles folder (default: a temporary one, converted there)")
    args = ap.parse_args(argv)
    results = []
    if args.scenario in (SCENE, "all"):
        results.append(run_scene(args))
    if args.scenario in (CITY, "all"):
        results.append(run_city(args))
    if args.scenario in (WINDOWS, "all"):
        results.extend(run_windows(args))
    if args.scenario == GUARD_EDGE:
        results.extend(run_windows(args, GUARD_EDGE))
    if args.scenario == BATCHED:
        results.extend(run_batched(args))
    if args.scenario == WORKER:
        results.extend(run_worker(args))
    if args.scenario == TILED:
        results.append(run_tiled(args))
    for out in results:
        if args.json:
            print(json.dumps(out))
        else:
            print("\n".join(f"{k:24s} {v}" for k, v in out.items()) + "\n")
    return 0


def run_scene(args) -> dict:
    scene = load_scene(ROOT / "data" / "womd" / f"{SCENE}.tfrecord")
    with tempfile.TemporaryDirectory() as tmp:
        rep = convert_scene(scene, Path(tmp), ConvertOptions(baseline=False))
        if rep.status != "ok":
            raise SystemExit(f"{SCENE}: conversion failed: {rep.reason}")
        env = SumoDrivingEnv(scene, Path(tmp) / SCENE,
                             EnvConfig(controlled="all", terminate_on=(), limits=REPLAY_LIMITS))
        moved = set(env.possible_agents) - set(env.bundle.parked)
        # the floor runs in its own process: libsumo 1.28 segfaulted in the step of a session
        # started, in the same process, after a session that moved and removed vehicles
        runs = [_in_fresh_process(run_raw, env.bundle.sumocfg, scene, moved, 1)
                for _ in range(args.episodes)]  # a fresh process per episode
        raw_secs, raw_steps = (sum(v) for v in zip(*runs))
        run_env(env, 1)  # warm-up: numba kernels load, SUMO files cached
        secs, agent_steps, sensors, peak = run_env(env, args.episodes)
        env.close()
    out = {
        "scene": SCENE,
        "agents": len(env.possible_agents),
        "agent_steps_per_s": round(agent_steps / secs, 1),
        "raw_sumo_steps_per_s": round(raw_steps / raw_secs, 1),
        "sensor_share": round(sensors / secs, 3),
        "peak_live_agents": peak,
        "mean_live_agents": round(agent_steps / (args.episodes * (scene.num_steps - 1)), 1),
        "env_steps_per_s": round(args.episodes * (scene.num_steps - 1) / secs, 1),
    }
    return out


def _window_episodes(env: SumoDrivingEnv, episodes: int) -> tuple[float, int]:
    """(seconds of reset + steps, agent-steps) of ``episodes`` seeded random windows."""
    total, agent_steps = 0.0, 0
    for ep in range(episodes):
        t0 = time.perf_counter()
        env.reset(seed=ep)
        while env.agents:
            acts = expert_actions(env)
            agent_steps += len(acts)
            env.step(acts)
        total += time.perf_counter() - t0
    return total, agent_steps


#: the windows measures: name -> (variant A, variant B) of EnvConfig settings, each a
#: (label, overrides) pair; both play the same seeded windows, alternating
WINDOW_VARIANTS = {
    WINDOWS: (("mirror", {"sumo_mirror": True}), ("no_mirror", {"sumo_mirror": False})),
    GUARD_EDGE: (("plain", {"sumo_mirror": False}),
                 ("guard_edge", {"sumo_mirror": False, "off_road_rule": "road_edge",
                                 "guard": GuardConfig(kind="gap")})),
}


def _window_bundles(tmp: Path):
    """(file, scene, bundle folder) of each window scene, converted into ``tmp``."""
    from converters import find_scene

    for f in WINDOW_SCENES:
        scene = find_scene(f, None)
        rep = convert_scene(scene, tmp, ConvertOptions(baseline=False))
        if rep.status != "ok":
            raise SystemExit(f"{f}: conversion failed: {rep.reason}")
        yield f, scene, tmp / scene.scenario_id


def run_windows(args, measure: str = WINDOWS) -> list[dict]:
    """Training's random 80-step windows (reset included, expert actions) of the window scenes
    under the two env variants of ``measure`` (:data:`WINDOW_VARIANTS`); medians of the
    repeats."""
    rows = []
    (la, ca), (lb, cb) = WINDOW_VARIANTS[measure]
    with tempfile.TemporaryDirectory() as tmp:
        for f, scene, bundle in _window_bundles(Path(tmp)):
            envs = {lab: SumoDrivingEnv(scene, bundle, EnvConfig(
                controlled="all", terminate_on=(), limits=REPLAY_LIMITS, start_window="random",
                max_steps=80, min_history=10, **over)) for lab, over in ((la, ca), (lb, cb))}
            rates: dict[str, list[float]] = {la: [], lb: []}
            steps = 0
            for lab in (la, lb):
                _window_episodes(envs[lab], 1)  # warm-up: numba kernels, files cached
            for _ in range(args.repeats):
                for lab in (la, lb):
                    secs, steps = _window_episodes(envs[lab], args.episodes)
                    rates[lab].append(steps / secs)
            for env in envs.values():
                env.close()
            a, b = (float(np.median(rates[lab])) for lab in (la, lb))
            rows.append({"scene": scene.scenario_id, "measure": measure,
                         "log_steps": scene.num_steps, "episodes": args.episodes,
                         "agent_steps": steps,
                         f"agent_steps_per_s_{la}": round(a, 1),
                         f"agent_steps_per_s_{lb}": round(b, 1),
                         f"runs_{la}": [round(r, 1) for r in rates[la]],
                         f"runs_{lb}": [round(r, 1) for r in rates[lb]],
                         "speedup": round(b / a, 2)})
    return rows


def _worker_steps(worker, steps: int) -> tuple[float, int]:
    """(seconds, agent-steps) of ``steps`` steps of a scene worker from its reset, under
    seeded random actions (the same in every run)."""
    rng = np.random.default_rng(0)
    acts = rng.uniform(-0.3, 0.3, (steps, worker.slots, 2)).astype(np.float32)
    t0, agent_steps = time.perf_counter(), 0
    worker.reset()
    for a in acts:
        agent_steps += worker.step(a)["agent_steps"]
    return time.perf_counter() - t0, agent_steps


def _alternate_workers(workers: dict, args) -> tuple[dict, int]:
    """Agent-steps/s of each worker over ``args.repeats`` rounds of ``args.steps`` steps,
    alternating (after a warm-up: numba kernels, every scene's env built); the workers are
    closed after. ``(label -> rates, agent-steps of the last run)``."""
    rates: dict = {lab: [] for lab in workers}
    for w in workers.values():
        _worker_steps(w, 40)
    steps = 0
    for _ in range(args.repeats):
        for lab, w in workers.items():
            secs, steps = _worker_steps(w, args.steps)
            rates[lab].append(steps / secs)
    for w in workers.values():
        w.close()
    return rates, steps


def run_worker(args) -> list[dict]:
    """The scene worker on the array API against the dict API (module doc)."""
    from magail_sumo.env.slot_worker import SceneSpec, SlotWorker

    cfg = EnvConfig(start_window="random", max_steps=80, min_history=10, sumo_mirror=False,
                    terminate_on=("collision", "off_road"))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for f, scene, bundle in _window_bundles(Path(tmp)):
            spec = SceneSpec(str(f), str(bundle), scene.scenario_id)
            workers = {lab: SlotWorker(spec, cfg, seed=0, slots=None)
                       for lab in ("dicts", "arrays")}
            workers["dicts"]._uses_arrays = lambda: False  # the worker's former path
            rates, steps = _alternate_workers(workers, args)
            a, b = (float(np.median(rates[lab])) for lab in ("dicts", "arrays"))
            rows.append({"scene": scene.scenario_id, "measure": WORKER,
                         "worker_steps": args.steps, "agent_steps": steps,
                         "agent_steps_per_s_dicts": round(a, 1),
                         "agent_steps_per_s_arrays": round(b, 1),
                         "runs_dicts": [round(r, 1) for r in rates["dicts"]],
                         "runs_arrays": [round(r, 1) for r in rates["arrays"]],
                         "speedup": round(b / a, 2)})
    return rows


def _rollouts_single(env: SumoDrivingEnv, worlds: int) -> tuple[float, int]:
    """(seconds, agent-steps) of ``worlds`` episodes of one env (the dict API)."""
    t0, agent_steps = time.perf_counter(), 0
    act = np.array([0.1, 0.0], np.float32)
    for w in range(worlds):
        env.reset(seed=w)
        while env.agents:
            agent_steps += len(env.agents)
            env.step(dict.fromkeys(env.agents, act))
    return time.perf_counter() - t0, agent_steps


def _rollouts_batched(env) -> tuple[float, int]:
    """(seconds, agent-steps) of one episode of a batched env (the array API)."""
    t0, agent_steps = time.perf_counter(), 0
    st = env.reset_arrays(seed=0)
    actions = np.zeros((len(env.fleet), 2), np.float32)
    actions[:, 0] = 0.1
    while not env.finished:
        agent_steps += int(st.live.sum())
        st = env.step_arrays(actions)
    return time.perf_counter() - t0, agent_steps


def run_batched(args) -> list[dict]:
    """The batched core against one env per rollout (module doc), per world count."""
    from magail_sumo.env.batched import BatchedSceneEnv

    scene = load_scene(ROOT / "data" / "womd" / f"{SCENE}.tfrecord")
    cfg = EnvConfig(controlled="all", start_step=scene.current_time_index, max_steps=80,
                    terminate_on=(), end_of_life=False, sumo_mirror=False)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        rep = convert_scene(scene, Path(tmp), ConvertOptions(baseline=False))
        if rep.status != "ok":
            raise SystemExit(f"{SCENE}: conversion failed: {rep.reason}")
        bundle = Path(tmp) / SCENE
        single = SumoDrivingEnv(scene, bundle, cfg)
        _rollouts_single(single, 1)  # warm-up: numba kernels load
        for worlds in args.worlds:
            t0 = time.perf_counter()
            batched = BatchedSceneEnv(scene, bundle, cfg, worlds=worlds)
            build = time.perf_counter() - t0
            _rollouts_batched(batched)
            rates: dict[str, list[float]] = {"single": [], "batched": []}
            for _ in range(args.repeats):
                secs, n = _rollouts_single(single, worlds)
                rates["single"].append(n / secs)
                secs, n = _rollouts_batched(batched)
                rates["batched"].append(n / secs)
            a, b = (float(np.median(rates[k])) for k in ("single", "batched"))
            rows.append({"scene": SCENE, "measure": BATCHED, "worlds": worlds,
                         "agents_at_once": len(batched.fleet),
                         "agent_steps_per_s_single": round(a, 1),
                         "agent_steps_per_s_batched": round(b, 1),
                         "runs_single": [round(r, 1) for r in rates["single"]],
                         "runs_batched": [round(r, 1) for r in rates["batched"]],
                         "build_s": round(build, 2), "speedup": round(b / a, 2)})
            batched.close()
        single.close()
    return rows

def run_tiled(args) -> dict:
    """A worker of the 10 womd14 train scenes, one per episode against one tiled env of all
    (module doc)."""
    import yaml

    from converters.scene_files import RecordRef
    from magail_sumo.env.slot_worker import PoolSpec, SlotWorker

    cfg = EnvConfig(start_window="random", max_steps=80, min_history=10, sumo_mirror=False,
                    terminate_on=("collision", "off_road"))
    split = yaml.safe_load((ROOT / "configs" / "splits" / "womd14.yaml").read_text())
    refs = tuple(RecordRef(str(ROOT / f)) for f in split["train"])
    with tempfile.TemporaryDirectory() as tmp:
        nets = str(args.networks or Path(tmp) / "networks")
        workers = {k: SlotWorker(PoolSpec(refs, nets, scenes_per_env=k), cfg, seed=0, slots=None)
                   for k in (1, len(refs))}
        rates, _ = _alternate_workers(workers, args)
    a, b = (float(np.median(rates[k])) for k in (1, len(refs)))
    return {"measure": TILED, "scenes": len(refs), "worker_steps": args.steps,
            "agent_steps_per_s_one_scene": round(a, 1),
            "agent_steps_per_s_tiled": round(b, 1),
            "runs_one_scene": [round(r, 1) for r in rates[1]],
            "runs_tiled": [round(r, 1) for r in rates[len(refs)]],
            "speedup": round(b / a, 2)}


if __name__ == "__main__":
    raise SystemExit(main())

