"""WOSAC 2025 realism metrics: agreement with the official tool, submission I/O, bad input."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from converters import load_scene
from magail_sumo.cli.main import main
from magail_sumo.evaluation import (
    ScenarioRollouts, SubmissionError, iter_submission, read_submission, validate_rollouts,
    write_submission,
)
from magail_sumo.evaluation.realism import METRIC_FIELDS, log_replay, scenario_metrics

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "data" / "womd" / "637f20cafde22ff8.tfrecord"
OTHER = ROOT / "data" / "womd" / "850c48d8bbfa008f.tfrecord"
CONSTVEL = ROOT / "data" / "wosac" / "constvel_637f20cafde22ff8.binproto"

# Official values of the constant-velocity submission (data/wosac/README.md).
OFFICIAL_CONSTVEL = {
    "metametric": 0.25824, "average_displacement_error": 2.5052812,
    "min_average_displacement_error": 2.0846887, "linear_speed_likelihood": 0.6471468,
    "linear_acceleration_likelihood": 0.12930943, "angular_speed_likelihood": 0.061595537,
    "angular_acceleration_likelihood": 0.3092796,
    "distance_to_nearest_object_likelihood": 0.23723939,
    "collision_indication_likelihood": 0.05286773, "time_to_collision_likelihood": 0.75434494,
    "distance_to_road_edge_likelihood": 0.40215302, "offroad_indication_likelihood": 0.07356792,
    "traffic_light_violation_likelihood": 0.99996877, "simulated_collision_rate": 0.6875,
    "simulated_offroad_rate": 0.265625, "simulated_traffic_light_violation_rate": 0.0,
}
# The two tables below were measured by running the official waymo-open-dataset sim-agents
# metrics (TF 2.12, 2025 config, waymo-open-dataset commit 99a4cb3) on the submissions that
# log_rollouts() / noisy_rollouts() build: they are the official tool's figures, not ours.
OFFICIAL_LOG = {
    "metametric": 0.826631427, "average_displacement_error": 0.0,
    "min_average_displacement_error": 0.0, "linear_speed_likelihood": 0.826528549,
    "linear_acceleration_likelihood": 0.53052479, "angular_speed_likelihood": 0.487326175,
    "angular_acceleration_likelihood": 0.656285584,
    "distance_to_nearest_object_likelihood": 0.400351167,
    "collision_indication_likelihood": 0.999968767, "time_to_collision_likelihood": 0.83621341,
    "distance_to_road_edge_likelihood": 0.559177697,
    "offroad_indication_likelihood": 0.999968767,
    "traffic_light_violation_likelihood": 0.999968767, "simulated_collision_rate": 0.25,
    "simulated_offroad_rate": 0.0, "simulated_traffic_light_violation_rate": 0.0,
}
OFFICIAL_NOISY = {
    "metametric": 0.726847768, "average_displacement_error": 0.521748662,
    "min_average_displacement_error": 0.339016885, "linear_speed_likelihood": 0.799796343,
    "linear_acceleration_likelihood": 0.210610643, "angular_speed_likelihood": 0.351109684,
    "angular_acceleration_likelihood": 0.37956205,
    "distance_to_nearest_object_likelihood": 0.386526972,
    "collision_indication_likelihood": 0.905993879, "time_to_collision_likelihood": 0.82012558,
    "distance_to_road_edge_likelihood": 0.556845546,
    "offroad_indication_likelihood": 0.859157443,
    "traffic_light_violation_likelihood": 0.999968767, "simulated_collision_rate": 0.3046875,
    "simulated_offroad_rate": 0.1171875, "simulated_traffic_light_violation_rate": 0.0,
}


@pytest.fixture(scope="module")
def scene():
    return load_scene(SCENE)


def noisy_rollouts(scene) -> ScenarioRollouts:
    """Log replay plus a per-rollout random walk (xy steps N(0, 0.08) m, heading steps
    N(0, 0.01) rad, ``default_rng(0)``, drawn rollout by rollout, agent by agent)."""
    base = log_replay(scene, 1)
    rng = np.random.default_rng(0)
    R, (_, A, T) = 32, base.shape
    x, y, h = (np.empty((R, A, T), np.float32) for _ in range(3))
    for r in range(R):
        for a in range(A):
            drift = np.cumsum(rng.normal(0, 0.08, (T, 2)), 0)
            turn = np.cumsum(rng.normal(0, 0.01, T))
            x[r, a] = base.x[0, a].astype(np.float64) + drift[:, 0]
            y[r, a] = base.y[0, a].astype(np.float64) + drift[:, 1]
            h[r, a] = base.heading[0, a].astype(np.float64) + turn
    return ScenarioRollouts(base.scenario_id, base.object_id, x, y,
                            np.repeat(base.z, R, 0), h)


def _check(ours: dict, official: dict) -> None:
    assert list(ours) == list(METRIC_FIELDS)
    bad = {k: (ours[k], v) for k, v in official.items() if not abs(ours[k] - v) <= 0.01}
    assert not bad, bad


def test_constvel_agrees_with_official(scene):
    (ro,) = read_submission(CONSTVEL)
    assert ro.shape == (32, 50, 80)
    _check(scenario_metrics(scene, ro), OFFICIAL_CONSTVEL)


def test_log_replay_agrees_with_official(scene):
    _check(scenario_metrics(scene, log_replay(scene)), OFFICIAL_LOG)


def test_noisy_log_agrees_with_official(scene):
    _check(scenario_metrics(scene, noisy_rollouts(scene)), OFFICIAL_NOISY)


def test_write_read_round_trip(tmp_path, scene):
    ro = noisy_rollouts(scene)
    path = tmp_path / "sub.binproto"
    write_submission(path, [ro], method_name="test")
    (back,) = read_submission(path)
    assert back.scenario_id == ro.scenario_id
    for k in ("object_id", "x", "y", "z", "heading"):
        np.testing.assert_array_equal(getattr(back, k), getattr(ro, k))
    validate_rollouts(back, scene)


# ------------------------------------------------------------------ bad input


def _bad(kind: str, good: ScenarioRollouts) -> ScenarioRollouts:
    """A broken variant of ``good`` (another scene's rollouts)."""
    x, y, z, h = good.x.copy(), good.y.copy(), good.z.copy(), good.heading.copy()
    ids = good.object_id
    if kind == "agents":
        ids, x, y, z, h = ids[1:], x[:, 1:], y[:, 1:], z[:, 1:], h[:, 1:]
    elif kind == "steps":
        x, y, z, h = x[..., :79], y[..., :79], z[..., :79], h[..., :79]
    elif kind == "nan":
        x[3, 1, 7] = np.nan
    return ScenarioRollouts(good.scenario_id, ids, x, y, z, h)


@pytest.mark.parametrize("kind, message", [
    ("agents", "scenario 850c48d8bbfa008f: wrong agent set (4 to simulate): missing agent(s) 617"),
    ("steps", "scenario 850c48d8bbfa008f: agent "),
    ("nan", "scenario 850c48d8bbfa008f: rollout 3 agent "),
    ("unknown", "scenario 850c48d8bbfa008f: no such scene among --scenes"),
])
def test_bad_scenario_is_reported_and_others_score(tmp_path, capsys, kind, message):
    other = log_replay(load_scene(OTHER))
    (good,) = read_submission(CONSTVEL)
    path = tmp_path / "sub.binproto"
    write_submission(path, [_bad(kind, other), good])
    scenes = [str(SCENE)] + ([] if kind == "unknown" else [str(OTHER)])
    rc = main(["realism", "--scenes", *scenes, "--submission", str(path), "--json"])
    out, err = capsys.readouterr()
    assert rc == 1
    rows = [json.loads(line) for line in out.splitlines()]
    assert [r["scenario_id"] for r in rows] == ["637f20cafde22ff8"]
    assert abs(rows[0]["metametric"] - OFFICIAL_CONSTVEL["metametric"]) <= 0.01
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and errors[0].startswith("error: " + message), err
    if kind == "steps":
        assert "79 simulated steps, expected 80" in errors[0]
    if kind == "nan":
        assert "non-finite x at simulated step 7" in errors[0]


def test_ragged_trajectories_are_one_line_errors(tmp_path):
    from converters.womd.protos import sim_agents_submission_pb2 as pb
    from magail_sumo.evaluation.submission import rollouts_to_proto

    (good,) = read_submission(CONSTVEL)
    msg = rollouts_to_proto(good)
    del msg.joint_scenes[5].simulated_trajectories[2].center_y[-1]
    dup = rollouts_to_proto(good)
    dup.joint_scenes[1].simulated_trajectories[0].object_id = \
        dup.joint_scenes[1].simulated_trajectories[1].object_id
    sub = pb.SimAgentsChallengeSubmission(scenario_rollouts=[msg, dup, rollouts_to_proto(good)])
    path = tmp_path / "sub.binproto"
    path.write_bytes(sub.SerializeToString())
    recs = list(iter_submission(path))
    assert [r.error is None for r in recs] == [False, False, True]
    agent = good.object_id[2]
    assert str(recs[0].error) == (f"scenario 637f20cafde22ff8: rollout 5 agent {agent}: "
                                  "79 steps of center_y, expected 80")
    assert "rollout 1: agent" in str(recs[1].error) and "\n" not in str(recs[1].error)
    with pytest.raises(SubmissionError):
        read_submission(path)


def test_text_table(capsys):
    rc = main(["realism", "--scenes", str(SCENE), "--submission", str(CONSTVEL)])
    out = capsys.readouterr().out
    assert rc == 0
    assert out.splitlines()[0].split() == ["field", "637f20cafde22ff8"]
    assert "metametric" in out and "0.258" in out


def test_scene_with_history_of_one_step_scores_all_80_simulated_steps():
    """A scene whose current step is 0 (ScenarioNet's 20-s scenes, nuScenes) is scored over all
    80 simulated steps, not from the WOSAC default's step 11 on."""
    import dataclasses

    from magail_sumo.evaluation.realism.metrics import compute_features
    from magail_sumo.evaluation.realism.trajectories import joint_trajectories

    sc = dataclasses.replace(load_scene(OTHER), current_time_index=0)
    ro = log_replay(sc, 2)
    feat = compute_features(sc, joint_trajectories(sc, ro))
    assert feat.valid.shape[-1] == 80
    assert feat.values["linear_speed"].shape[-1] == 80
    assert scenario_metrics(sc, ro, validate=False)["simulated_collision_rate"] == 0.0


# ------------------------------------------------------------------------------ submission messages
def _submission_error(tmp_path, edit) -> str:
    from converters.womd.protos import sim_agents_submission_pb2 as pb
    from magail_sumo.evaluation import iter_submission, read_submission
    from magail_sumo.evaluation.submission import rollouts_to_proto

    (good,) = read_submission(CONSTVEL)
    msg = rollouts_to_proto(good)
    edit(msg)
    path = tmp_path / "sub.binproto"
    path.write_bytes(pb.SimAgentsChallengeSubmission(scenario_rollouts=[msg]).SerializeToString())
    [rec] = list(iter_submission(path))
    return str(rec.error)


@pytest.mark.parametrize("field", ["center_x", "center_y", "heading"])
@pytest.mark.parametrize("rollout, agent", [(0, 0), (5, 2)])
def test_short_trajectory_field_is_named(tmp_path, field, rollout, agent):
    def edit(msg):
        del getattr(msg.joint_scenes[rollout].simulated_trajectories[agent], field)[-1]
    text = _submission_error(tmp_path, edit)
    assert text.endswith(f"79 steps of {field}, expected 80"), text


def test_huge_finite_coordinate_is_out_of_range_not_non_finite(scene_637f):
    from magail_sumo.evaluation import SubmissionError, read_submission, validate_rollouts

    (good,) = read_submission(CONSTVEL)
    x = np.array(good.x, np.float64)
    x[3, 1, 7] = 1e308
    ro = dataclasses.replace(good, x=x)
    with pytest.raises(SubmissionError) as err:
        validate_rollouts(ro, scene_637f)
    text = str(err.value)
    assert (f"rollout 3 agent {int(good.object_id[1])}: x 1e+308 out of range (|x| > 1e+07 m) "
            "at simulated step 7") in text, text
    assert "non-finite" not in text


def test_submission_that_is_a_device_or_fifo_is_refused_at_once(tmp_path):
    """``realism --submission /dev/zero`` (or a FIFO) is one line, not a read until memory
    runs out or a hang."""
    import os
    import time

    fifo = tmp_path / "sub.binproto"
    os.mkfifo(fifo)
    t0 = time.monotonic()
    for path, what in (("/dev/zero", "is a character device"), (fifo, "is a FIFO")):
        with pytest.raises(SubmissionError, match=what):
            list(iter_submission(path))
    assert time.monotonic() - t0 < 5
