"""A driving policy on a whole SUMO city against SUMO's default drivers, from SUMO's own outputs.

:func:`evaluate_city` runs two simulations of one plain SUMO scenario (a ``.sumocfg``, e.g.
``data/sumo/ingolstadt21``) over the same time window and summarises both with
:func:`~magail_sumo.evaluation.traffic.sumo_outputs.summarise` (travel, waiting and lost time
of the trips that arrived, throughput, mean edge speed, teleports, SUMO's collision count):

* the policy (method: its name): :class:`~magail_sumo.env.city_env.SumoCityEnv` as training
  plays a city with the default env settings (those the checkpoint loader checks a policy
  against), closed loop, the policy acting for every agent each 0.1-s step; at most
  ``max_agents`` agents at once (a chosen vehicle waits, SUMO-driven, for a free place), the
  rest of the demand SUMO background traffic. It runs in a fresh worker process (libsumo
  allows one simulation per process) with a timeout, SUMO writing the outputs through the
  env's ``sumo_args``;
* ``sumo``: the ``sumo`` binary, every vehicle driven by SUMO's default model.

Fair comparison: both runs start from the same SUMO state — the scenario's begin time plus
``warmup_s`` seconds simulated by SUMO alone (the env's warm-up, 1-s steps, saved once and
loaded with ``--load-state`` by both runs; none when ``warmup_s`` is 0: both start at the
scenario's begin) — and end at the same time, ``steps + 1`` steps of 0.1 s later (the env's
reset makes one step). Both use the env's SUMO settings (0.1-s steps, teleporting disabled, so
jams show as waiting time, collisions only reported) and the same SUMO seed (the warm-up, as in
training, runs with the env's own ``sumo_seed``, 0). SUMO's outputs
cover that window: a trip counts when it ends inside it (its travel time may include time
before it, spent in the warm-up, the same way in both runs); edge speeds and throughput are
over the window.

An agent that an event ends (collision, off-road, red light) is taken out of SUMO: it never
arrives and its trip is left out (``removed``); an agent ending within the destination radius
of its route's end is taken out too and its trip counts as arrived. Agents still driving at
the window's end are taken out like the vehicles SUMO has not finished: neither counts.
``collisions`` is SUMO's own count in both runs; the env's events are the policy row's
``terminations``.

Outputs: ``OUT/city/<scenario>/<method>/{tripinfo,edgedata,statistics}.xml``, the warm state
``OUT/city/<scenario>/warm.xml.gz``, ``OUT/city.json`` (rows of :data:`ROW_FIELDS` per scenario
and method; rows of other scenarios or the same window are kept) and a ``city`` entry in
``OUT/manifest.json`` (created when the folder has none, so ``magail-sumo report`` works on a
city-only folder).
"""

from __future__ import annotations

import json
import os
import math
import shutil
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from magail_sumo.sim.sumo_config import (SumoConfigError, config_of, scenario_name,
                                         vtype_classes)
from magail_sumo.inputs import InputFileError, read_json
from magail_sumo.agents import env_settings, rollout
from magail_sumo.env.city_env import (VEHICLE_CLASSES, CityEnvConfig, SumoCityEnv, demand_args,
                                      scenario_inputs)
from magail_sumo.env.config import EnvConfig
from magail_sumo.errors import MagailSumoError
from magail_sumo.evaluation.protocol import DEFAULT_TIMEOUT_S, EvaluationError, log, rollout_seed
from magail_sumo.evaluation.storage import previous_manifest, versions
from magail_sumo.evaluation.city_kinematics import (ACCEL_WINDOW_S, FEATURES, Group, fcd_group,
                                                   human_counts, js)
from magail_sumo.evaluation.traffic.distributions import BINS
from magail_sumo.evaluation.traffic.sumo_outputs import (SumoRunError, SumoRunSummary,
                                                         output_args, run_sumo_outputs,
                                                         summarise)
from magail_sumo.outputs import (claim_output_dir, inside, inside_dir, one_line, printable,
                                 safe_name, write_text)
from magail_sumo.agents.specs import BASELINES
from magail_sumo.sim.session import SessionConfig
from magail_sumo.workers import run_one

#: method name of SUMO's default drivers
SUMO_METHOD = "sumo"
#: env events counted in a policy row's ``terminations`` (those that end an agent)
EVENTS = ("collision", "off_road", "red_light", "destination")
#: events that take an agent out of SUMO before its trip's end (``removed``)
REMOVING = ("collision", "off_road", "red_light")
#: fields of a :data:`SumoRunSummary`, in order
SUMMARY_FIELDS = tuple(f.name for f in fields(SumoRunSummary))
#: columns of a ``city.json`` row: the scenario, method and window (SUMO time of day, s), every
#: :class:`SumoRunSummary` field, then the policy's own counts (0 / {} for ``sumo``)
ROW_FIELDS = ("scenario", "method", "begin_s", "end_s", "seed", *SUMMARY_FIELDS, "agents",
              "agent_steps", "terminations", "removed", "peak_agents", "speed_js_humans",
              "accel_js_humans", "tight_turns", "unblocked", "jumped")
#: row fields that rows written before them lack (read as NaN)
LATER_FIELDS = ("peak_agents", "speed_js_humans", "accel_js_humans", "tight_turns",
                "unblocked", "jumped")
#: in a scenario's city folder: the speed / acceleration counts of agents, SUMO's drivers and
#: the recorded humans (:mod:`~magail_sumo.evaluation.city_kinematics`)
KINEMATICS_FILE = "kinematics.json"
CITY_FILE = "city.json"


@dataclass(frozen=True)
class CitySettings:
    """How a city is evaluated.

    :param steps: 0.1-s steps of the policy run after its first (reset) step.
    :param warmup_s: seconds SUMO drives alone before the window (s; 0: none).
    :param max_agents: policy-driven vehicles alive at once.
    :param control_fraction: share of the vehicles that may become agents (seeded).
    :param seed: SUMO's seed in both runs and the agent choice; the policy gets
        ``rollout_seed(seed, 0)``.
    :param deterministic: a checkpoint policy acts with its mean action.
    :param noise_scale: a sampling policy's noise scale (None: the policy's own; see
        :func:`~magail_sumo.policies.make_policy`).
    :param timeout_s: seconds each run may take (None: no limit).
    :param agent_classes: SUMO vehicle classes that may become agents (the rest, and every
        vehicle with stops, stay SUMO-driven).
    :param agent_tight_turns: vehicles whose route turns tighter than they can (SUMO's
        on-the-spot turnarounds) become agents too (default: SUMO drives them;
        ``CityEnvConfig.agent_tight_turns``).
    :param unblock_s: SUMO-driven vehicles that have waited this long (s) next to an agent
        standing as long on a junction stop giving way to standing agents (0: never;
        ``CityEnvConfig.unblock_s``).
    :param demand_scale: the scenario's demand times this in both runs (SUMO's ``--scale``;
        ``CityEnvConfig.demand_scale``; 1: as it is).
    :param fcd: record the policy's run as SUMO FCD (``city/<scenario>/<method>/fcd/``) with a
        ``.sumocfg`` that replays it in ``sumo-gui`` on the city's network.
    :param humans: expert data of recorded humans (``magail-sumo expert``'s folder): the
        rows' ``speed_js_humans`` / ``accel_js_humans`` compare the agents' and SUMO's drivers'
        distributions with theirs (:mod:`~magail_sumo.evaluation.city_kinematics`; None:
        NaN).
    """

    steps: int = 3000
    warmup_s: float = 600.0
    max_agents: int = 64
    control_fraction: float = 1.0
    seed: int = 0
    deterministic: bool = False
    noise_scale: float | None = None
    timeout_s: float | None = DEFAULT_TIMEOUT_S
    agent_classes: tuple[str, ...] = ("passenger",)
    agent_tight_turns: bool = False
    unblock_s: float = 10.0
    demand_scale: float = 1.0
    fcd: bool = False
    humans: str | None = None

    def __post_init__(self) -> None:
        bad = sorted(set(self.agent_classes) - set(VEHICLE_CLASSES))
        if bad or not self.agent_classes:
            raise EvaluationError(f"--city-agent-classes: not SUMO vehicle classes: "
                                  f"{', '.join(bad) or '(none given)'}")
        for ok, what in ((self.steps >= 1, f"--city-steps must be >= 1, got {self.steps}"),
                         (self.warmup_s >= 0, f"--city-warmup-s must be >= 0, got "
                                              f"{self.warmup_s}"),
                         (self.max_agents >= 1, f"--city-max-agents must be >= 1, got "
                                                f"{self.max_agents}"),
                         (0.0 < self.control_fraction <= 1.0,
                          f"--city-control-fraction must be in (0, 1], got "
                          f"{self.control_fraction}"),
                         (math.isfinite(self.unblock_s) and self.unblock_s >= 0,
                          f"--city-unblock-s must be >= 0, got {self.unblock_s}"),
                         (math.isfinite(self.demand_scale) and self.demand_scale > 0,
                          f"--city-demand-scale must be > 0, got {self.demand_scale}")):
            if not ok:
                raise EvaluationError(what)


@dataclass(frozen=True)
class PolicyJob:
    """Work of the policy run's worker process (paths as strings: picklable)."""

    sumocfg: str
    out_dir: str
    state_copy: str
    spec: str
    settings: CitySettings


@dataclass
class PolicyRun:
    """What the policy run reports besides SUMO's outputs.

    :param begin_s, end_s: the window (SUMO time of day, s).
    :param agents: vehicles that were agents at some point.
    :param agent_steps: agent actions applied (agents × steps).
    :param peak_agents: most agents alive at once.
    :param terminations: per :data:`EVENTS` event, agents it ended.
    :param completed: agents ended at their destination (their trips count as arrived).
    :param action_counts: the env's fixed-up actions (missing, unknown, non-finite, clipped).
    :param state: the saved warm state (None: no warm-up).
    :param fcd: the run's SUMO FCD file and the ``.sumocfg`` that replays it in ``sumo-gui``,
        or None when not recorded.
    :param kinematics: speed / acceleration counts of the agents
        (:class:`~magail_sumo.evaluation.city_kinematics.Group` ``as_json``).
    :param tight_turns: chosen vehicles left SUMO-driven because their route turns tighter
        than they can (``SumoCityEnv.tight_turns``).
    :param unblocked: SUMO-driven vehicles released from giving way to standing agents
        (``SumoCityEnv.unblocked``).
    :param jumped: SUMO-driven vehicles moved on past a junction where they and an agent stood
        in each other's path (``SumoCityEnv.jumped``).
    """

    begin_s: float
    end_s: float
    agents: int
    agent_steps: int
    terminations: dict[str, int]
    completed: list[str]
    action_counts: dict[str, int] = field(default_factory=dict)
    state: str | None = None
    fcd: tuple[str, str] | None = None
    peak_agents: int = 0
    kinematics: dict = field(default_factory=dict)
    tight_turns: int = 0
    unblocked: int = 0
    jumped: int = 0


#: in a method's city folder: the ids of the agents that ended at their destination
COMPLETED_FILE = "completed.json"
#: SUMO's run: its FCD sampled every second (read into kinematics.json, then removed)
FCD_1S = "fcd_1s.xml"


def completed_ids(method_dir: str | Path) -> list[str]:
    """The :data:`COMPLETED_FILE` ids of a method's city folder ([] when absent or unusable)."""
    path = Path(method_dir) / COMPLETED_FILE
    try:
        ids = read_json(path, expected="a list of vehicle ids") if path.exists() else []
    except InputFileError:
        return []
    return [i for i in ids if isinstance(i, str)] if isinstance(ids, list) else []


def city_config(path: str | Path) -> Path:
    """The SUMO configuration ``path`` names: the file itself (any name SUMO's scenarios use:
    ``*.sumocfg``, ``run.sumo.cfg``, or an XML ``<configuration>``) or the one a scenario
    folder holds; :class:`EvaluationError` (one line) otherwise."""
    path = Path(path)
    try:
        found = config_of(path)
    except SumoConfigError as exc:
        raise EvaluationError(str(exc)) from None
    if found is None:
        what = ("holds no SUMO configuration" if path.is_dir() else
                "not found" if not path.exists() else "is not a SUMO configuration")
        raise EvaluationError(f"{path}: {what} (--city takes a SUMO scenario's configuration, "
                              "e.g. its .sumocfg, or the folder holding it)")
    return found


def check_sumocfg(path: str | Path) -> tuple[str, ...]:
    """Check ``path`` is a usable city scenario (a SUMO configuration or a folder holding one,
    :func:`city_config`, naming its net and route files,
    :func:`~magail_sumo.env.city_env.scenario_inputs`); returns what of its configuration
    SUMO will not be given (outputs, logs, ports, ...);
    :class:`~magail_sumo.errors.MagailSumoError` naming the file otherwise."""
    inputs, _ = scenario_inputs(city_config(path))
    return inputs.dropped


def check_policy(spec: str, deterministic: bool = False,
                 noise_scale: float | None = None) -> None:
    """Refuse a spec that cannot drive a city (a baseline, an unusable policy) up front."""
    if spec in BASELINES:
        raise EvaluationError(f"--policy {spec}: a city needs a driving policy (random, "
                              "pretrained[:NAME], a checkpoint or module:factory); SUMO's "
                              "default drivers run alongside as method 'sumo'")
    # lazy: the report imports this module (city.json) in workers that run without torch
    from magail_sumo.policies import make_policy

    make_policy(spec, 0, deterministic, noise_scale)


def run_policy(job: PolicyJob) -> PolicyRun:
    """Worker entry point (module level, picklable): the policy drives the city for the
    window (module doc); SUMO writes its outputs into ``job.out_dir``."""
    st = job.settings
    # lazy: the report imports this module (city.json) in workers that run without torch
    from magail_sumo.policies import make_policy

    policy = make_policy(job.spec, rollout_seed(st.seed, 0), st.deterministic, st.noise_scale)
    # the env the policy needs: its optional features, action layout and gap guard
    cfg = CityEnvConfig.from_env(EnvConfig(**env_settings(policy)), max_agents=st.max_agents,
                                 control_fraction=st.control_fraction, warmup_s=st.warmup_s,
                                 agent_classes=st.agent_classes,
                                 agent_tight_turns=st.agent_tight_turns,
                                 unblock_s=st.unblock_s, max_steps=st.steps,
                                 demand_scale=st.demand_scale)
    env = SumoCityEnv(job.sumocfg, cfg, sumo_args=tuple(output_args(job.out_dir)))
    state = env.warm_state()
    if state is not None:
        shutil.copyfile(state, job.state_copy)
    seen: set[str] = set()
    agent_steps = peak = 0
    agents = Group(env.dt)
    ends = dict.fromkeys(EVENTS, 0)
    completed: list[str] = []
    began: list[float] = []

    def count(step) -> None:
        nonlocal agent_steps, peak
        seen.update(step.agents)
        agent_steps += len(step.agents)
        peak = max(peak, len(step.agents))
        f = env.fleet
        live = f.live()
        agents.add(f.names_of(live), f.speed[live])
        for a, done in step.terminations.items():
            reason = step.infos[a].get("reason")
            if done and reason in ends:
                ends[reason] += 1
                if reason == "destination":
                    completed.append(a)

    if st.fcd:
        env.record_fcd()
    try:  # the reset makes one SUMO step: the window begins a step before its time
        rollout(env, policy, count, seed=st.seed, max_steps=st.steps, until_empty=False,
                live_only=True,
                on_reset=lambda *_: began.append(round(float(env.sumo_time) - env.dt, 3)))
        begin = began[0]
        end = round(float(env.sumo_time), 3)
        counts = dict(env.action_counts)
        tight, unblocked, jumped = env.tight_turns, env.unblocked, env.jumped
    finally:
        env.close()  # SUMO writes its outputs here
    fcd = None
    if st.fcd:
        folder = inside_dir(job.out_dir, "fcd")
        files = env.write_fcd(inside(folder, f"{safe_name(env.scenario_id)}.fcd.xml"))
        fcd = (str(files.fcd), str(files.sumocfg))
    return PolicyRun(begin, end, len(seen), agent_steps, ends, completed, counts,
                     job.state_copy if state is not None else None, fcd, peak,
                     agents.as_json(), tight, unblocked, jumped)


def _sumo_default(sumocfg: Path, out_dir: Path, run: PolicyRun, st: CitySettings
                  ) -> tuple[SumoRunSummary, dict]:
    """SUMO's default drivers over the policy run's window, from the same state and with the
    env's SUMO settings (module doc); with their speed / acceleration counts
    (:func:`~magail_sumo.evaluation.city_kinematics.fcd_group`, vehicles of the classes that
    may be agents, from an FCD sampled every second that is read and removed)."""
    sess = SessionConfig()
    fcd = inside(out_dir, FCD_1S)
    extra = ["--step-length", str(sess.step_length), "--time-to-teleport",
             str(sess.time_to_teleport), "--collision.action", sess.collision_action,
             "--fcd-output", str(fcd), "--device.fcd.period", f"{ACCEL_WINDOW_S:g}",
             "--fcd-output.attributes", "speed,type"]
    extra += demand_args(st.demand_scale)  # the same demand as the policy's run
    if run.state is not None:
        extra += ["--load-state", run.state]  # the begin time is the state's
    begin = None if run.state is not None else run.begin_s
    summary = run_sumo_outputs(sumocfg, out_dir, begin=begin, end=run.end_s,
                               seed=st.seed, extra_args=extra, timeout_s=st.timeout_s)
    try:
        inputs = scenario_inputs(sumocfg)[0]
        group = fcd_group(fcd, st.agent_classes,
                          vtype_classes([*inputs.routes, *inputs.additional]))
    finally:
        fcd.unlink(missing_ok=True)
    return summary, group.as_json()


def _row(scenario: str, method: str, run: PolicyRun, st: CitySettings, s: SumoRunSummary,
         policy: bool, humans: dict | None, kinematics: dict) -> dict:
    ends = run.terminations if policy else {}
    dist = js(kinematics, humans)
    return {"scenario": scenario, "method": method, "begin_s": run.begin_s,
            "end_s": run.end_s, "seed": st.seed, **asdict(s),
            "agents": run.agents if policy else 0,
            "agent_steps": run.agent_steps if policy else 0,
            "terminations": dict(ends), "removed": sum(ends.get(e, 0) for e in REMOVING),
            "peak_agents": run.peak_agents if policy else 0,
            "speed_js_humans": dist["speed"], "accel_js_humans": dist["accel"],
            "tight_turns": run.tight_turns if policy else 0,
            "unblocked": run.unblocked if policy else 0,
            "jumped": run.jumped if policy else 0}


@dataclass
class CityResult:
    """What :func:`evaluate_city` wrote: its ``city.json`` rows and one-line errors."""

    rows: list[dict]
    errors: list[str]


def evaluate_city(policy: str, sumocfgs: list[str | Path], out: str | Path,
                  settings: CitySettings | None = None, name: str | None = None) -> CityResult:
    """Evaluate ``policy`` on every city scenario against SUMO's default drivers (module doc).

    A scenario whose run fails (an exception, a worker that dies or runs past the timeout:
    killed) is reported on one line (stderr and ``errors``) and the others go on.

    :param name: the policy's method name (default :func:`method_name` of the spec).
    :raises EvaluationError: an unusable spec or setting, a scenario file that is no SUMO
        scenario, a name that is ``sumo``.
    """
    st = settings or CitySettings()
    out = Path(out)
    check_policy(policy, st.deterministic, st.noise_scale)
    # lazy: the report imports this module (city.json) in workers that run without torch
    from magail_sumo.policies import method_name

    method = name if name is not None else method_name(policy)
    if not method.strip() or not method.isprintable() or len(method) > 100:
        raise EvaluationError(f"--name {printable(method)!r}: must be a non-empty printable "
                              "name of at most 100 characters")
    if method == SUMO_METHOD:
        raise EvaluationError(f"--name {method}: is the name of SUMO's default drivers")
    cfgs: dict[str, Path] = {}
    dropped: dict[str, tuple[str, ...]] = {}
    for f in sumocfgs:
        path = city_config(f)
        sid = scenario_name(path)
        if sid in cfgs:
            raise EvaluationError(f"{path}: scenario {sid} given twice ({cfgs[sid]})")
        dropped[sid] = check_sumocfg(path)
        if dropped[sid]:
            log(f"city {printable(sid)}: not given to SUMO from its configuration: "
                + printable("; ".join(dropped[sid]), 600))
        cfgs[sid] = path
    humans = _humans(st.humans)
    claim_output_dir(out, "evaluate", ["manifest.json", "city", CITY_FILE])
    rows: list[dict] = []
    errors: list[str] = []
    windows: dict[str, dict] = {}
    for sid, cfg in cfgs.items():
        base = inside(out, "city", safe_name(sid))
        mine = inside(base, safe_name(method))
        sumo_dir = inside(base, SUMO_METHOD)
        for d in (mine, sumo_dir):
            shutil.rmtree(d, ignore_errors=True)  # a failed run leaves no stale outputs
        inside_dir(out, "city", safe_name(sid), safe_name(method))
        state = inside(base, "warm.xml.gz")
        state.unlink(missing_ok=True)
        log(f"city {printable(sid)}: {method} driving up to {st.max_agents} agents for "
            f"{st.steps} steps after a {st.warmup_s:g} s warm-up")
        res = run_one(run_policy, PolicyJob(str(cfg.resolve()), str(mine.resolve()),
                                            str(state.resolve()), policy, st),
                      timeout_s=st.timeout_s)
        if not res.ok:
            what = "timed out" if res.kind == "timeout" else "failed"
            errors.append(f"{cfg}: method {method}: city run {what}: {res.reason}")
            log(f"error: {errors[-1]}")
            continue
        run: PolicyRun = res.value
        try:
            # the agents that reached their destination (their trips count as arrived): the
            # report's travel-time figure reads them
            write_text(inside(mine, COMPLETED_FILE), json.dumps(sorted(run.completed)))
            mine_sum = summarise(mine, run.completed)
            log(f"city {printable(sid)}: {SUMO_METHOD} over the same window "
                f"({run.begin_s:.1f}-{run.end_s:.1f} s)")
            sumo_sum, sumo_kin = _sumo_default(cfg, inside_dir(base, SUMO_METHOD), run, st)
        except (SumoRunError, MagailSumoError) as exc:
            errors.append(one_line(exc, 600))
            log(f"error: {errors[-1]}")
            continue
        rows += [_row(sid, method, run, st, mine_sum, True, humans, run.kinematics),
                 _row(sid, SUMO_METHOD, run, st, sumo_sum, False, humans, sumo_kin)]
        write_text(inside(base, KINEMATICS_FILE), json.dumps(
            {"bins": {name: BINS[f] for f, name in FEATURES},
             "methods": {method: run.kinematics, SUMO_METHOD: sumo_kin}, "humans": humans,
             "note": f"vehicles of classes {list(st.agent_classes)}; {method}: its agents every "
                     f"0.1 s; {SUMO_METHOD}: SUMO's run of the window, every "
                     f"{ACCEL_WINDOW_S:g} s; accel: speed change over {ACCEL_WINDOW_S:g} s"}))
        windows[sid] = {"scenario": sid, "sumocfg": str(cfg.resolve()), "begin_s": run.begin_s,
                        "end_s": run.end_s, "action_fixes": run.action_counts,
                        "sumo_options_dropped": list(dropped[sid])}
        if run.fcd is not None:
            windows[sid]["fcd"] = run.fcd[0]
            log(f"city {printable(sid)}: FCD of the {method} run -> {run.fcd[0]} (replay: "
                f"sumo-gui -c {run.fcd[1]})")
    if rows:
        write_rows(out, rows)
        _record(out, policy, method, st, windows)
    return CityResult(rows, errors)


def _humans(expert_dir: str | None) -> dict | None:
    """The recorded humans' counts (None without ``expert_dir``); one line when unusable."""
    if expert_dir is None:
        return None
    try:
        return human_counts(expert_dir)
    except MagailSumoError as exc:
        raise EvaluationError(f"--city-humans: {one_line(exc, 300)}") from None


# ------------------------------------------------------------------------------ city.json
def _json_value(v):
    return None if isinstance(v, float) and not math.isfinite(v) else v


def write_rows(out: Path, rows: list[dict]) -> Path:
    """Merge ``rows`` into ``out/city.json``: an old row is kept unless the new rows have its
    scenario and method, or its scenario with another window or seed."""
    path = inside(out, CITY_FILE)
    old: list[dict] = []
    if path.is_file():
        try:
            old, _ = read_rows(out)
        except MagailSumoError:
            old = []  # unreadable: replaced
    new = {(r["scenario"], r["method"]) for r in rows}
    window = {r["scenario"]: (r["begin_s"], r["end_s"], r["seed"]) for r in rows}
    kept = [r for r in old if (r["scenario"], r["method"]) not in new
            and window.get(r["scenario"], (r["begin_s"], r["end_s"], r["seed"]))
            == (r["begin_s"], r["end_s"], r["seed"])]
    merged = [{k: _json_value(v) for k, v in r.items()} for r in kept + rows]
    write_text(path, json.dumps(merged, indent=1, allow_nan=False) + "\n")
    return path


def read_rows(folder: str | Path) -> tuple[list[dict], Path]:
    """The rows of ``folder/city.json`` ([] when there is none) and its path; null figures
    read as NaN. :class:`EvaluationError` naming the file and field for a bad file."""
    path = Path(folder) / CITY_FILE
    if not os.path.lexists(path):
        return [], path
    try:  # a FIFO, a device or a dangling link: one line, not silence
        data = read_json(path, expected="a city.json")
    except InputFileError as exc:
        raise EvaluationError(f"unreadable: {one_line(exc, 300)}") from None
    if not isinstance(data, list):
        raise EvaluationError(f"{path}: expected a list of rows, got {type(data).__name__}")
    rows = []
    for k, r in enumerate(data):
        if not isinstance(r, dict):
            raise EvaluationError(f"{path}: row {k}: expected an object")
        missing = [f for f in ROW_FIELDS if f not in r and f not in LATER_FIELDS]
        if missing:
            raise EvaluationError(f"{path}: row {k}: missing field {missing[0]}")
        for f in ("scenario", "method"):
            if not isinstance(r[f], str):
                raise EvaluationError(f"{path}: row {k}: {f} must be a string")
        row = {f: r[f] for f in ("scenario", "method")}
        for f in ROW_FIELDS[2:]:
            v = r.get(f)
            if f == "terminations":
                if not isinstance(v, dict) or not all(
                        isinstance(n, int) and not isinstance(n, bool) for n in v.values()):
                    raise EvaluationError(f"{path}: row {k}: terminations must map events "
                                          "to counts")
                row[f] = {str(e): int(n) for e, n in v.items()}
            elif v is None:
                row[f] = float("nan")
            elif isinstance(v, (int, float)) and not isinstance(v, bool):
                row[f] = v
            else:
                raise EvaluationError(f"{path}: row {k}: {f} must be a number, got "
                                      f"{printable(repr(v), 40)}")
        rows.append(row)
    return rows, path


def _record(out: Path, policy: str, method: str, st: CitySettings, windows: dict) -> None:
    """Record the city run in ``out/manifest.json`` (created minimal when absent)."""
    path = inside(out, "manifest.json")
    man = previous_manifest(out)
    if not man:
        man = {"scenes": [], "methods": [], "policy": method, "policy_spec": policy,
               "seed": st.seed, "deterministic": bool(st.deterministic),
               "versions": versions()}
    old = man.get("city") if isinstance(man.get("city"), dict) else {}
    scenarios = {s.get("scenario"): s for s in old.get("scenarios", []) if isinstance(s, dict)}
    scenarios.update(windows)
    methods = [m for m in old.get("methods", []) if isinstance(m, str)]
    methods = list(dict.fromkeys(methods + [method, SUMO_METHOD]))
    man["city"] = {"file": CITY_FILE, "policy": method, "policy_spec": policy,
                   "methods": methods, **asdict(st), "scenarios": list(scenarios.values())}
    write_text(path, json.dumps(man, indent=2) + "\n")
