"""Leader sensor (``observation.leader``): gap and closing speed to the road user ahead."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR
from magail_sumo.sensors.base import Boxes, EgoState, SensorInput
from magail_sumo.sensors.observation import ObservationConfig, observation_names
from magail_sumo.sensors.units.leader import Leader

CFG = ObservationConfig(leader=True, leader_range=50.0)


def _read(x, y, yaw, speed, length, width, ego_yaw=0.0):
    """Leader reading of road user 0 (the agent) among boxes given in its ego frame, the whole
    scene turned by ``ego_yaw``."""
    c, s = np.cos(ego_yaw), np.sin(ego_yaw)
    x, y = np.asarray(x, float), np.asarray(y, float)
    boxes = Boxes(c * x - s * y + 3.0, s * x + c * y - 7.0, np.asarray(yaw, float) + ego_yaw,
                  np.asarray(length, float), np.asarray(width, float),
                  np.asarray(speed, float))
    ego = EgoState(np.array([0]), np.array([speed[0]], float), np.zeros((1, 2)),
                   np.zeros((1, 2)), np.zeros(1))
    return Leader(CFG, None).read(SensorInput(None, boxes, ego, 0))[0]


@pytest.mark.parametrize("turn", [0.0, 1.3, -2.6])
def test_leader_gap_and_closing_speed(turn):
    # agent; car in its path 20 m ahead; car beside (3 m left); car behind; car beyond range
    x, y = [0, 20, 10, -8, 60], [0, 0.5, 3.0, 0, 0]
    yaw, speed = [0, 0, 0, 0, 0], [10, 6, 0, 30, 0]
    length, width = [4.5, 4.0, 4.0, 4.0, 4.0], [2.0, 2.0, 2.0, 2.0, 2.0]
    gap, closing = _read(x, y, yaw, speed, length, width, turn)
    assert gap == pytest.approx(20 - 4.25, abs=1e-4) and closing == pytest.approx(4.0, abs=1e-4)
    # the car ahead comes towards the agent: closing speed 10 + 6
    gap, closing = _read(x, y, [0, np.pi, 0, 0, 0], speed, length, width, turn)
    assert closing == pytest.approx(16.0, abs=1e-4)
    # nobody in the path within range: the range and 0
    keep = [0, 2, 3, 4]
    got = _read(*(np.asarray(v)[keep] for v in (x, y, yaw, speed, length, width)),
                ego_yaw=turn)
    assert got.tolist() == [50.0, 0.0]


def test_leader_names_and_range_refusal():
    names = observation_names(CFG)
    assert names[-2:] == ["leader_gap", "leader_closing"]
    with pytest.raises(ValueError, match="leader_range"):
        ObservationConfig(leader=True, leader_range=0.0)


@pytest.mark.sumo
def test_env_leaders_on_a_real_scene():
    """On a real scene replayed from the log, the agents' leaders are found, and the gap
    changes over a step by about minus the closing speed times the step (0.1 s)."""
    from converters import load_scene
    from magail_sumo.env import REPLAY_LIMITS, EnvConfig, SumoDrivingEnv, expert_actions

    sid = "637f20cafde22ff8"
    scene = load_scene(WOMD_DIR / f"{sid}.tfrecord")
    env = SumoDrivingEnv(scene, ROOT / "networks" / sid, EnvConfig(
        controlled="all", start_step=10, max_steps=20, terminate_on=(), limits=REPLAY_LIMITS,
        observation=CFG, sumo_mirror=False))
    names = observation_names(CFG)
    g, c = names.index("leader_gap"), names.index("leader_closing")
    try:
        obs, _ = env.reset(seed=0)
        led = [a for a in obs if obs[a][g] < 30.0]
        assert len(led) >= 3
        before = {a: obs[a][[g, c]].copy() for a in led}
        obs, *_ = env.step(expert_actions(env))
        err = [abs((obs[a][g] - before[a][0]) + 0.1 * before[a][1]) for a in led if a in obs]
        # the same leader a step later (most pairs): the gap moved by -closing * dt
        assert np.median(err) < 0.1
    finally:
        env.close()


def test_evaluation_observes_with_the_policys_leader_sensor():
    from magail_sumo.env import EnvConfig
    from magail_sumo.policies import policy_observation

    ob = policy_observation(EnvConfig(observation=ObservationConfig(leader=True,
                                                                    leader_range=30.0)))
    assert ob.leader and ob.leader_range == 30.0 and ob.route_points == ()
    assert policy_observation(EnvConfig()) == ObservationConfig()
