"""Faults found by an adversarial run: nothing hangs, every failure is one line, batches go on.

Real worker processes and real SUMO throughout; the job and policy functions below are
module-level so that spawned workers can import them.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from magail_sumo.cli.main import main
from magail_sumo.workers import run_jobs

ROOT = Path(__file__).resolve().parents[1]
WOMD_DIR = ROOT / "data" / "womd"
SID = "850c48d8bbfa008f"  # the smallest bundled scene
SCENE = WOMD_DIR / f"{SID}.tfrecord"
MARKER_ENV = "MAGAIL_SUMO_TEST_MARKER"


# ------------------------------------------------------------------ jobs run in workers
def fault_job(job: tuple) -> object:
    """A job that returns, exits, is killed, hangs, stops itself or raises."""
    what, value = job
    if what == "exit":
        os._exit(3)
    if what == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    if what == "sleep":
        time.sleep(600)
    if what == "stop":
        os.kill(os.getpid(), signal.SIGSTOP)
    if what == "raise":
        raise ValueError(f"bad job\nsecond line {value}")
    return value * 2


class _StoppingPolicy:
    """Stops its own process (SIGSTOP) at the first action: a hung SUMO worker."""

    def act(self, observations):
        marker = os.environ.get(MARKER_ENV)
        if marker:
            Path(marker).write_text("stopped")
        os.kill(os.getpid(), signal.SIGSTOP)
        return {}


def stopping_policy(seed: int) -> _StoppingPolicy:
    return _StoppingPolicy()


def stopping_controller(libsumo, time_s: float) -> None:
    """A SUMO controller whose process stops itself after the first steps."""
    if time_s >= 0.5:
        os.kill(os.getpid(), signal.SIGSTOP)


def raising_factory(seed: int):
    raise RuntimeError("no weights here")


def not_a_policy(seed: int):
    return 42


class _PartialPolicy:
    """Acts for every other agent only, plus one made-up agent."""

    def act(self, observations):
        names = sorted(observations)
        out = {n: np.zeros(2, np.float32) for n in names[::2]}
        out["no-such-agent"] = np.zeros(2, np.float32)
        return out


def partial_policy(seed: int) -> _PartialPolicy:
    return _PartialPolicy()


def env_action_counts(bundle: str) -> dict:
    """Three env steps with actions missing for every other agent and one unknown agent."""
    from converters import load_scene
    from magail_sumo.env import EnvConfig, SumoDrivingEnv

    env = SumoDrivingEnv(load_scene(SCENE), bundle, EnvConfig(controlled="all",
                                                              terminate_on=()))
    obs, _ = env.reset(seed=0)
    policy = _PartialPolicy()
    expected_missing = 0
    for _ in range(3):
        expected_missing += len(env.agents) - len(sorted(env.agents)[::2])
        obs, *_ = env.step(policy.act({a: obs[a] for a in env.agents}))
    counts = dict(env.action_counts)
    env.close()
    return {"counts": counts, "expected_missing": expected_missing}


# ------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def bundle_root(bundled_networks) -> Path:
    return bundled_networks(SID)


def _dense_scene(n_junction: int = 40, n_in: int = 4, n_out: int = 4, steps: int = 91):
    """Road lanes into and out of a junction whose ``n_junction`` lanes all connect to each
    other (and to every road lane around): exponentially many junction paths."""
    from magail_sumo.scene import Lane, LaneType, RoadMap, Scene, Tracks

    def line(p, q, n=6):
        t = np.linspace(0.0, 1.0, n)[:, None]
        return np.column_stack([p + (q - p) * t, np.zeros(n)])

    ins, outs = list(range(1, n_in + 1)), list(range(100, 100 + n_out))
    junction = list(range(200, 200 + n_junction))
    lanes, end_in, start_out = [], {}, {}
    for k, a in enumerate(np.linspace(0, np.pi, n_in, endpoint=False)):
        d = np.array([np.cos(a), np.sin(a)])
        end_in[ins[k]] = d * 20
        lanes.append(Lane(ins[k], line(d * 120, d * 20), LaneType.SURFACE_STREET, 25.0,
                          exit_lanes=tuple(junction)))
        start_out[outs[k]] = -d * 20
        lanes.append(Lane(outs[k], line(-d * 20, -d * 120), LaneType.SURFACE_STREET, 25.0,
                          entry_lanes=tuple(junction)))
    for m, j in enumerate(junction):
        others = tuple(x for x in junction if x != j)
        lanes.append(Lane(j, line(end_in[ins[m % n_in]], start_out[outs[(m // n_in) % n_out]]),
                          LaneType.SURFACE_STREET, 25.0, interpolating=True,
                          entry_lanes=tuple(ins) + others, exit_lanes=tuple(outs) + others))
    return Scene("dense-junction", np.arange(steps) * 0.1, Tracks.empty(steps),
                 RoadMap(lanes=tuple(lanes)))


# ------------------------------------------------------------------ 1. dead / stuck pool workers
def test_pool_reports_dead_and_stuck_workers_and_finishes_the_others():
    jobs = [("ok", 1), ("exit", 0), ("kill", 0), ("sleep", 0), ("stop", 0), ("raise", 7),
            ("ok", 2)]
    clock = time.monotonic()
    res = list(run_jobs(fault_job, jobs, workers=3, timeout_s=15.0, ordered=True))
    assert time.monotonic() - clock < 60
    assert [r.index for r in res] == list(range(len(jobs)))
    kinds = [r.kind for r in res]
    assert kinds == ["ok", "died", "died", "timeout", "timeout", "error", "ok"]
    assert [res[0].value, res[-1].value] == [2, 4]
    assert "exit code 3" in res[1].reason and "exit code -9" in res[2].reason
    assert res[3].reason == "timed out after 15 s (worker killed)"
    assert res[5].reason == "ValueError: bad job second line 7" and not res[5].expected
    assert all("\n" not in r.reason for r in res)


@pytest.mark.sumo
def test_convert_workers_report_hung_scenes_and_bad_records(tmp_path):
    from converters.sumo.batch import convert_files
    from converters.sumo.scenario import ConvertOptions

    bad = tmp_path / "bad.tfrecord"
    bad.write_bytes(b"\x00" * 40)
    clock = time.monotonic()
    rows = list(convert_files([SCENE, bad, WOMD_DIR / "2831b6fde0420b0d.tfrecord"],
                              tmp_path / "out", workers=2,
                              options=ConvertOptions(baseline=False), timeout_s=0.05))
    assert time.monotonic() - clock < 30
    assert [r.status for r in rows if r.status == "unreadable"] == ["unreadable"]
    scenes = [r for r in rows if r.status != "unreadable"]
    assert [r.scenario_id for r in scenes] == [SID, "2831b6fde0420b0d"]
    # the first scene may finish while the parent reads the last file; the last one cannot
    assert scenes[1].status == "failed"
    for r in scenes:
        assert r.status == "ok" or r.reason == f"{r.scenario_id}: timed out after 0.05 s " \
            "(worker killed)"


# ------------------------------------------------------------------ 2. stopped SUMO worker in evaluate
@pytest.mark.sumo
def test_evaluate_reports_a_stopped_worker_and_goes_on(tmp_path, bundle_root, monkeypatch,
                                                       capsys):
    marker = tmp_path / "stopped"
    monkeypatch.setenv(MARKER_ENV, str(marker))
    out = tmp_path / "eval"
    clock = time.monotonic()
    rc = main(["evaluate", "--policy", f"{__name__}:stopping_policy", "--baselines", "constvel",
               "--scenes", str(SCENE), "--networks", str(bundle_root), "--rollouts", "1",
               "--workers", "1", "--timeout-s", "20", "--out", str(out)])
    assert time.monotonic() - clock < 120
    err = capsys.readouterr().err
    assert rc == 1
    assert marker.read_text() == "stopped"  # the worker really was stopped, then killed
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and "timed out after 20 s (worker killed)" in lines[0], err
    assert f"scenario {SID}" in lines[0]
    assert (out / "rollouts" / "constvel" / f"{SID}.parquet").is_file()  # the rest went on


@pytest.mark.sumo
def test_controlled_sumo_run_that_stops_times_out(tmp_path, bundle_root):
    from magail_sumo.evaluation.traffic import sumo_outputs as so

    cfg = bundle_root / SID / f"{SID}.sumocfg"
    clock = time.monotonic()
    with pytest.raises(so.SumoRunError, match="controlled SUMO run timed out after 8 s"):
        so.run_sumo_outputs(cfg, tmp_path / "o", controller=f"{__name__}:stopping_controller",
                            timeout_s=8)
    assert time.monotonic() - clock < 60


# ------------------------------------------------------------------ 3. dense junction, time budget
@pytest.mark.sumo
def test_dense_junction_converts_within_seconds(tmp_path):
    from converters.sumo.scenario import ConvertOptions, convert_scene
    from converters.sumo.topology import plan_network

    scene = _dense_scene(40)
    clock = time.monotonic()
    plan = plan_network(scene)
    assert time.monotonic() - clock < 10
    assert len(plan.junction_lanes) == 40
    assert len({(c.from_edge, c.to_edge) for c in plan.connections}) == 16  # every in -> out
    dense = [u for u in plan.unconverted if u["reason"].startswith("densely connected")]
    assert sorted(u["id"] for u in dense) == [1, 2, 3, 4]
    rep = convert_scene(scene, tmp_path, ConvertOptions(baseline=False))
    assert time.monotonic() - clock < 30
    assert rep.status == "ok", rep.reason


def test_conversion_over_its_time_budget_fails_with_the_reason(tmp_path):
    from converters import load_scene
    from converters.sumo.scenario import ConvertOptions, convert_scene

    rep = convert_scene(load_scene(SCENE), tmp_path, ConvertOptions(baseline=False,
                                                                    time_budget_s=1e-6))
    assert rep.status == "failed"
    assert rep.reason.startswith(f"{SID}: ") and "time budget of 1e-06 s exceeded" in rep.reason


# ------------------------------------------------------------------ 4. top-level handler, batches
def test_unexpected_error_is_one_line_naming_command_and_input(monkeypatch, capsys):
    from magail_sumo.cli import inspect

    def boom(args):
        raise ValueError("something\nbroke")

    monkeypatch.setattr(inspect, "run", boom)
    assert main(["inspect", str(SCENE)]) == 1
    err = capsys.readouterr().err.splitlines()
    assert err[0] == f"error: magail-sumo inspect: {SCENE}: ValueError: something broke"
    assert err[1] == "(run with --debug for the traceback)" and len(err) == 2
    assert main(["--debug", "inspect", str(SCENE)]) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and err.rstrip().endswith("ValueError: something broke")
    assert main(["inspect", str(SCENE), "--debug"]) == 1
    assert "Traceback" in capsys.readouterr().err

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(inspect, "run", interrupted)
    assert main(["inspect", str(SCENE)]) == 130


def test_inspect_skip_bad_goes_on_past_a_failing_scene(monkeypatch, capsys):
    from magail_sumo.scene import Scene

    real = Scene.summary

    def summary(self):
        if self.scenario_id == SID:
            raise KeyError("lost")
        return real(self)

    monkeypatch.setattr(Scene, "summary", summary)
    other = WOMD_DIR / "2831b6fde0420b0d.tfrecord"
    assert main(["inspect", "--skip-bad", "--json", str(SCENE), str(other)]) == 0
    out, err = capsys.readouterr()
    assert '"2831b6fde0420b0d"' in out
    assert f"scene {SID}: KeyError: 'lost'" in err
    assert main(["inspect", str(SCENE), str(other)]) == 1


def test_expert_goes_on_past_failing_scenes(tmp_path):
    from magail_sumo.env.vec_env import SceneSpec
    from magail_sumo.expert import record_expert

    specs = [SceneSpec(str(SCENE), str(tmp_path / "no-bundle"), SID),
             SceneSpec(str(SCENE), str(tmp_path / "no-bundle"), "no-such-scene")]
    seen = []
    meta = record_expert(specs, tmp_path / "expert", on_error=lambda s, r: seen.append(r),
                         timeout_s=120)
    assert meta["scenes"] == [] and len(meta["failed"]) == 2 and len(seen) == 2
    assert all("\n" not in r for r in seen)
    assert "no-such-scene" in seen[1]


# ------------------------------------------------------------------ 5. replay arguments
@pytest.mark.parametrize("args, message", [
    (["--fps", "0"], "argument --fps: 0 is outside 1..100"),
    (["--fps", "-3"], "argument --fps: -3 is outside 1..100"),
    (["--size", "0"], "argument --size: 0 is outside 64..4096"),
    (["--size", "100000"], "argument --size: 100000 is outside 64..4096"),
    (["--fps", "ten"], "argument --fps: 'ten' is not an int"),
])
def test_replay_refuses_bad_numbers(tmp_path, capsys, args, message):
    with pytest.raises(SystemExit) as exc:
        main(["replay", str(SCENE), "--out", str(tmp_path / "v.gif"), *args])
    assert exc.value.code == 2
    assert capsys.readouterr().err.rstrip().endswith(message)


def test_replay_refuses_an_unwritable_out_before_the_slow_work(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    clock = time.monotonic()
    assert main(["replay", str(SCENE), "--out", str(blocker / "v.gif")]) == 1
    assert time.monotonic() - clock < 5
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("error: magail-sumo replay: ")
    assert f"{blocker / 'v.gif'}: cannot be written ({blocker} is not a folder)" in err[0]
    assert main(["replay", str(SCENE), "--out", "/proc/no/v.gif"]) == 1
    assert "/proc/no/v.gif: cannot be written (" in capsys.readouterr().err
    (tmp_path / "d.gif").mkdir()
    assert main(["replay", str(SCENE), "--out", str(tmp_path / "d.gif")]) == 1
    assert "d.gif: is a folder" in capsys.readouterr().err


def test_timeout_flag_is_checked(capsys):
    for cmd in (["convert", str(SCENE), "--out", "x"],
                ["evaluate", "--policy", "constvel", "--scenes", str(SCENE), "--out", "x"],
                ["expert", str(SCENE), "--out", "x"]):
        with pytest.raises(SystemExit):
            main([*cmd, "--timeout-s", "0"])
        assert "argument --timeout-s: 0 is outside" in capsys.readouterr().err


# ------------------------------------------------------------------ 6. raising policy factory
@pytest.mark.parametrize("factory, problem", [
    ("raising_factory", "could not be created: RuntimeError: no weights here"),
    ("not_a_policy", "the factory returned int, which has no act(observations) method"),
])
def test_raising_policy_factory_is_one_line(tmp_path, capsys, factory, problem):
    spec = f"{__name__}:{factory}"
    rc = main(["evaluate", "--policy", spec, "--baselines", "none", "--scenes", str(SCENE),
               "--out", str(tmp_path / "e")])
    assert rc == 1
    err = capsys.readouterr().err.splitlines()
    assert err == [f"error: magail-sumo evaluate: policy {spec}: {problem}"]


def test_unloadable_checkpoint_is_one_line(tmp_path, capsys):
    ckpt = tmp_path / "broken.pt"
    ckpt.write_bytes(b"not a checkpoint")
    rc = main(["evaluate", "--policy", str(ckpt), "--baselines", "none", "--scenes", str(SCENE),
               "--out", str(tmp_path / "e")])
    assert rc == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("error: magail-sumo evaluate: ")
    assert str(ckpt) in err[0] and "Traceback" not in err[0]


# ------------------------------------------------------------------ 7. missing / unknown actions
@pytest.mark.sumo
def test_env_counts_missing_and_unknown_actions(bundle_root):
    from magail_sumo.workers import run_one

    res = run_one(env_action_counts, str(bundle_root / SID), timeout_s=300)
    assert res.ok, res.reason
    counts = res.value["counts"]
    assert counts["missing"] == res.value["expected_missing"] > 0
    assert counts["unknown"] == 3 and counts["clipped"] == 0
    assert counts["nonfinite"] == counts["missing"]


def test_action_summary_words_the_counts():
    from magail_sumo.env.actions import action_summary

    assert action_summary({"missing": 0, "unknown": 0, "departed": 4, "nonfinite": 0,
                           "clipped": 0}) == ""
    line = action_summary({"missing": 12, "unknown": 3, "departed": 1, "nonfinite": 14,
                           "clipped": 1})
    assert line == ("policy gave no action for 12 agent-step(s) (those agents coasted: zero "
                    "acceleration and steering); 3 action(s) for unknown agents ignored; 2 "
                    "non-finite action(s) replaced by 0; 1 action(s) outside [-1, 1] clipped")


@pytest.mark.sumo
def test_evaluate_logs_a_policys_missing_actions(tmp_path, bundle_root, capfd):
    rc = main(["evaluate", "--policy", f"{__name__}:partial_policy", "--baselines", "none",
               "--scenes", str(SCENE), "--networks", str(bundle_root), "--rollouts", "1",
               "--workers", "1", "--out", str(tmp_path / "e")])
    err = capfd.readouterr().err
    assert rc == 0, err
    warn = [ln for ln in err.splitlines() if ln.startswith("warning:")]
    assert len(warn) == 1, err
    assert warn[0].startswith(f"warning: scenario {SID}: method {__name__}:partial_policy "
                              "rollout(s) 0: policy gave no action for ")
    assert "action(s) for unknown agents ignored" in warn[0]
    # counted in the manifest and shown in the report
    man = json.loads((tmp_path / "e" / "manifest.json").read_text())
    (fix,) = man["action_fixes"]
    assert fix["scenario_id"] == SID and fix["method"] == man["policy"]
    assert fix["missing"] > 0 and fix["unknown"] > 0
    assert main(["report", str(tmp_path / "e")]) == 0
    html = (tmp_path / "e" / "report" / "report.html").read_text()
    assert "Policy actions fixed up by the env" in html


# ------------------------------------------------------------------ vec env: every wait bounded
@pytest.mark.sumo
def test_vec_env_large_request_to_a_stopped_worker_times_out(bundle_root):
    from magail_sumo.env import EnvConfig
    from magail_sumo.env.vec_env import MultiSceneVecEnv, SceneSpec, VecEnvWorkerError

    spec = SceneSpec(str(SCENE), str(bundle_root / SID), SID)
    venv = MultiSceneVecEnv([spec], EnvConfig(controlled=3, max_steps=10), timeout_s=120.0)
    try:
        venv.reset()
        venv.timeout_s = 3.0
        os.kill(venv._procs[0].pid, signal.SIGSTOP)
        # distinct arrays (pickle would share one): far beyond a pipe's 64 KiB
        replay = [np.zeros((venv.num_envs, 2), np.float32) for _ in range(20_000)]
        clock = time.monotonic()
        with pytest.raises(VecEnvWorkerError, match="did not read its request within 3 s"):
            venv.set_state([(0, replay)])
        assert time.monotonic() - clock < 30
        assert not venv._procs[0].is_alive()
    finally:
        venv.close()
