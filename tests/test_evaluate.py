"""magail-sumo evaluate: WOSAC-protocol rollouts of the baselines and a policy on real scenes."""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from conftest import ROOT, PartialPolicy, WOMD_DIR
from converters import load_scene
from magail_sumo import agents, policies
from magail_sumo.cli.main import main
from magail_sumo.agents import constant_velocity as cv
from magail_sumo.evaluation import methods, protocol, runner, storage
from magail_sumo.evaluation.submission import iter_submission, sim_agent_ids, validate_rollouts

SID = "850c48d8bbfa008f"
R = 2


class _StopPolicy:
    """A pluggable policy: brake, no steering."""

    def __init__(self, seed: int) -> None:
        self.seed = seed

    def act(self, observations):
        return {a: np.array([-1.0, 0.0], np.float32) for a in observations}


def stop_policy(seed: int) -> _StopPolicy:
    return _StopPolicy(seed)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    out = tmp_path_factory.mktemp("eval")
    sub = out / "random.binproto"
    rc = main(["evaluate", "--policy", "random", "--scenes", str(WOMD_DIR / f"{SID}.tfrecord"),
               "--rollouts", str(R), "--out", str(out), "--seed", "7", "--workers", "2",
               "--export-submission", str(sub)])
    assert rc == 0
    return out, load_scene(WOMD_DIR / f"{SID}.tfrecord")


@pytest.mark.sumo
def test_parquet_layout_and_manifest(run):
    out, scene = run
    man = json.loads((out / "manifest.json").read_text())
    assert man["methods"] == ["random", "logreplay", "constvel", "sumo"]
    assert man["rollouts"] == R and man["seed"] == 7 and man["steps"] == 80
    assert man["scenes"][0]["scenario_id"] == SID and "pyarrow" in man["versions"]
    ids = sim_agent_ids(scene)
    cur = scene.current_time_index
    for m in man["methods"]:
        df = pd.read_parquet(out / "rollouts" / m / f"{SID}.parquet")
        assert tuple(df.columns) == storage.COLUMNS
        assert len(df) == R * len(ids) * (cur + 1 + 80)
        assert set(df["method"].astype(str)) == {m}
        ro = storage.read_rollouts(out / "rollouts" / m / f"{SID}.parquet", scene)
        validate_rollouts(ro, scene, R, 80)
        # the history is the log
        h = df[(df.step == cur) & (df.rollout == 1)].sort_values("object_id")
        rows = [int(np.flatnonzero(scene.tracks.id == i)[0]) for i in h.object_id]
        assert np.allclose(h.x, scene.tracks.x[rows, cur], atol=1e-3)
        if m in ("random", "sumo"):
            assert not np.allclose(ro.x[0], ro.x[1]), f"{m}: rollouts do not differ"


@pytest.mark.sumo
def test_sumo_starts_from_the_log(run):
    out, scene = run
    ro = storage.read_rollouts(out / "rollouts" / "sumo" / f"{SID}.parquet", scene)
    tr, cur = scene.tracks, scene.current_time_index
    rows = [int(np.flatnonzero(tr.id == i)[0]) for i in ro.object_id]
    err = np.hypot(ro.x[:, :, 0] - tr.x[rows, cur + 1], ro.y[:, :, 0] - tr.y[rows, cur + 1])
    assert np.median(err) < 1.0


@pytest.mark.sumo
def test_exported_submission(run):
    out, scene = run
    (rec,) = list(iter_submission(out / "random.binproto"))
    assert rec.error is None and rec.scenario_id == SID
    validate_rollouts(rec.rollouts, scene, R, 80)
    ro = storage.read_rollouts(out / "rollouts" / "random" / f"{SID}.parquet", scene)
    assert np.allclose(rec.rollouts.x, ro.x)


@pytest.mark.sumo
def test_seeded_and_pluggable_policy(bundled_networks):
    f = str(WOMD_DIR / f"{SID}.tfrecord")
    bundle = str(bundled_networks.bundle(SID))
    spec = f"{__name__}:stop_policy"
    batches = [runner.Batch(f, SID, bundle, "random", (0,), 3),
               runner.Batch(f, SID, bundle, "random", (0,), 3),
               runner.Batch(f, SID, bundle, spec, (0,), 3)]
    sys.path.insert(0, str(WOMD_DIR.parents[1] / "tests"))
    got = [(b.spec, ro) for b, ro, err, _ in runner.run_batches(batches, 2) if err is None]
    assert len(got) == 3
    rand = [ro for s, ro in got if s == "random"]
    assert np.array_equal(rand[0].x, rand[1].x)  # same seed, same rollout
    stop = next(ro for s, ro in got if s == spec)
    step = np.hypot(np.diff(stop.x[0], axis=1), np.diff(stop.y[0], axis=1))
    assert step[:, -10:].max() < step[:, :3].max() + 1e-6 or step.max() < 0.05


def test_policy_specs(tmp_path):
    assert isinstance(policies.make_policy("random", 0), agents.RandomPolicy)
    assert isinstance(policies.make_policy(f"{__name__}:stop_policy", 0), _StopPolicy)
    ckpt = tmp_path / "agent.ckpt"
    ckpt.write_bytes(b"x")
    with pytest.raises(agents.PolicyError, match="no policy loader"):
        policies.make_policy(str(ckpt), 0)
    policies.POLICY_LOADERS[".ckpt"] = lambda path, seed: _StopPolicy(seed)
    try:
        assert isinstance(policies.make_policy(str(ckpt), 5), _StopPolicy)
        assert policies.method_name(str(ckpt)) == "agent"
    finally:
        del policies.POLICY_LOADERS[".ckpt"]
    with pytest.raises(agents.PolicyError, match="not a method"):
        policies.make_policy("nonsense", 0)
    a = agents.RandomPolicy(1).act({"2": np.zeros(3), "1": np.zeros(3)})
    assert set(a) == {"1", "2"} and all(np.all(np.abs(v) <= 1) for v in a.values())


def test_loaders_get_the_deterministic_choice(tmp_path):
    """A loader with a ``deterministic`` keyword gets evaluation's choice; a (path, seed) one
    is called as before; factories and ``random`` ignore it."""
    ckpt = tmp_path / "agent.ckpt"
    ckpt.write_bytes(b"x")
    seen = []
    policies.POLICY_LOADERS[".ckpt"] = lambda path, seed, deterministic=False: \
        seen.append((seed, deterministic)) or _StopPolicy(seed)
    try:
        policies.make_policy(str(ckpt), 5)
        policies.make_policy(str(ckpt), 6, deterministic=True)
        assert seen == [(5, False), (6, True)]
        policies.POLICY_LOADERS[".ckpt"] = lambda path, seed: _StopPolicy(seed)
        assert policies.make_policy(str(ckpt), 7, deterministic=True).seed == 7
    finally:
        del policies.POLICY_LOADERS[".ckpt"]
    assert isinstance(policies.make_policy("random", 0, deterministic=True), agents.RandomPolicy)
    assert policies.make_policy(f"{__name__}:stop_policy", 3, deterministic=True).seed == 3
    # the choice travels with a batch into the workers (and its single-rollout retries)
    b = runner.Batch("f", SID, "b", "random", (0, 1), 3, True)
    assert b.deterministic and not runner.Batch("f", SID, "b", "random", (0,), 3).deterministic


def test_constant_velocity_fill():
    scene = load_scene(WOMD_DIR / f"{SID}.tfrecord")
    ids = sim_agent_ids(scene)
    tr, cur = scene.tracks, scene.current_time_index
    x, y, yaw = methods.constant_velocity(scene, ids)
    r = int(np.flatnonzero(tr.id == ids[0])[0])
    assert np.isclose(x[0, 9], tr.x[r, cur] + 10 * 0.1 * tr.vx[r, cur], atol=1e-4)
    track = cv.Track.empty(len(ids), 80)
    track.x[0, :5], track.y[0, :5], track.yaw[0, :5], track.speed[0, :5] = 1.0, 2.0, 0.0, 10.0
    x, y, _ = cv.fill_constant_velocity(scene, ids, track)
    assert np.isclose(x[0, 5], 2.0) and np.isclose(x[0, 14], 11.0) and np.allclose(y[0], 2.0)


def test_bad_scene_is_reported_and_others_continue(tmp_path, capsys):
    bad = tmp_path / "bad.tfrecord"
    bad.write_bytes(b"\x00" * 40)
    rc = main(["evaluate", "--policy", "constvel", "--baselines", "logreplay", "--scenes",
               str(bad), str(WOMD_DIR / f"{SID}.tfrecord"), "--rollouts", "2",
               "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 1
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and "bad.tfrecord" in lines[0]
    assert (tmp_path / "o" / "rollouts" / "constvel" / f"{SID}.parquet").is_file()
    rc = main(["evaluate", "--policy", "nonsense", "--scenes", str(WOMD_DIR / f"{SID}.tfrecord"),
               "--out", str(tmp_path / "p")])
    assert rc == 1 and "nonsense: not a method" in capsys.readouterr().err


def test_method_names(tmp_path):
    """Issue 14: a checkpoint is named after its run, not ``latest``; ``--name`` names the policy
    in the rollouts and the manifest; a built-in's name is refused."""
    ckdir = tmp_path / "magail_run" / "checkpoints"
    ckdir.mkdir(parents=True)
    for stem in ("latest", "update_000020"):
        (ckdir / f"{stem}.pt").write_bytes(b"x")
    assert policies.method_name(str(ckdir / "latest.pt")) == "magail_run"
    assert policies.method_name(str(ckdir / "update_000020.pt")) == "magail_run-update_000020"
    out = tmp_path / "ev"
    assert main(["evaluate", "--policy", "constvel", "--name", "cv_named", "--baselines",
                 "logreplay", "--scenes", str(WOMD_DIR / f"{SID}.tfrecord"), "--rollouts", "1",
                 "--out", str(out)]) == 0
    man = json.loads((out / "manifest.json").read_text())
    assert man["methods"] == ["cv_named", "logreplay"] and man["policy"] == "cv_named"
    assert (out / "rollouts" / "cv_named" / f"{SID}.parquet").is_file()
    assert set(pd.read_parquet(out / "rollouts" / "cv_named" / f"{SID}.parquet").method) == \
        {"cv_named"}
    with pytest.raises(protocol.EvaluationError, match="built-in"):
        runner.evaluate([str(WOMD_DIR / f"{SID}.tfrecord")], "constvel", tmp_path / "e2",
                    n_rollouts=1, baselines=["logreplay"], name="logreplay")


def test_progress_counts_every_rollout(tmp_path):
    """``progress("rollouts", done, total)`` after each method of a scene: the last call is
    the total, the counts never go back."""
    calls = []
    runner.evaluate([str(WOMD_DIR / f"{SID}.tfrecord")], "constvel", tmp_path / "ev",
                    n_rollouts=3, baselines=["logreplay"], progress=lambda *c: calls.append(c))
    assert [c[0] for c in calls] == ["rollouts"] * len(calls) and calls[-1][1:] == (6, 6)
    assert [c[1] for c in calls] == sorted(c[1] for c in calls)


# ------------------------------------------- faults: stopped workers, bad policies, missing actions
SCENE = WOMD_DIR / f"{SID}.tfrecord"


MARKER_ENV = "MAGAIL_SUMO_TEST_MARKER"


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


def raising_factory(seed: int):
    raise RuntimeError("no weights here")


def not_a_policy(seed: int):
    return 42


def partial_policy(seed: int) -> PartialPolicy:
    return PartialPolicy()


@pytest.mark.sumo
def test_evaluate_reports_a_stopped_worker_and_goes_on(tmp_path, bundled_networks, monkeypatch,
                                                       capsys):
    marker = tmp_path / "stopped"
    monkeypatch.setenv(MARKER_ENV, str(marker))
    out = tmp_path / "eval"
    clock = time.monotonic()
    rc = main(["evaluate", "--policy", f"{__name__}:stopping_policy", "--baselines", "constvel",
               "--scenes", str(SCENE), "--networks", str(bundled_networks(SID)), "--rollouts", "1",
               "--workers", "1", "--timeout-s", "20", "--out", str(out)])
    assert time.monotonic() - clock < 300  # generous: the stopped worker would never answer
    err = capsys.readouterr().err
    assert rc == 1
    assert marker.read_text() == "stopped"  # the worker really was stopped, then killed
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and "timed out after 20 s (worker killed)" in lines[0], err
    assert f"scenario {SID}" in lines[0]
    assert (out / "rollouts" / "constvel" / f"{SID}.parquet").is_file()  # the rest went on


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


@pytest.mark.sumo
def test_evaluate_logs_a_policys_missing_actions(tmp_path, bundled_networks, capfd):
    rc = main(["evaluate", "--policy", f"{__name__}:partial_policy", "--baselines", "none",
               "--scenes", str(SCENE), "--networks", str(bundled_networks(SID)), "--rollouts", "1",
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


def test_export_submission_into_a_folder_is_refused_before_the_rollouts(tmp_path, capsys):
    """``--export-submission DIR`` (a folder) or under a file: one line naming the path given
    and the problem (not a temporary file), before any rollout; nothing is written."""
    folder, blocker = tmp_path / "subs", tmp_path / "file"
    folder.mkdir()
    blocker.write_text("x")
    for given, problem in ((folder, "is a folder (give a file name like sub.binproto)"),
                           (blocker / "s.binproto", f"cannot be written ({blocker} is not a "
                                                    "folder)")):
        out = tmp_path / "eval"
        assert main(["evaluate", "--policy", "constvel", "--baselines", "none", "--rollouts",
                     "1", "--scenes", str(WOMD_DIR / f"{SID}.tfrecord"), "--out", str(out),
                     "--export-submission", str(given)]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"error: magail-sumo evaluate: {given}: {problem}"], err
        assert not out.exists()
    assert sorted(os.listdir(tmp_path)) == ["file", "subs"] and os.listdir(folder) == []


@pytest.mark.sumo
def test_an_unusable_bundle_in_networks_is_named_not_passed_over(tmp_path, capsys):
    """--networks holding the scene's bundle with a FIFO for a file (or a deep report): one line
    names it and why; the scene is converted anew and evaluated."""
    import os
    import shutil

    sid = "637f20cafde22ff8"  # the shipped bundle
    nets = tmp_path / "nets"
    shutil.copytree(ROOT / "networks" / sid, nets / sid)
    (nets / sid / "conversion.json").unlink()
    os.mkfifo(nets / sid / "conversion.json")
    assert main(["evaluate", "--policy", "constvel", "--baselines", "sumo", "--rollouts", "1",
                 "--scenes", str(WOMD_DIR / f"{sid}.tfrecord"), "--networks", str(nets),
                 "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "conversion.json: bundle file is a FIFO (named pipe), expected a regular file: " \
           "bundle not used" in err
