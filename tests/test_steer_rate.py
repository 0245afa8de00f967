"""Steering rate limit (``env.limits.max_steer_rate``): the bicycle model's front wheel turns at
most so fast, in the env on a real scene, and a checkpoint trained with it carries it into
evaluation."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR, tiny_checkpoint
from magail_sumo.config import ConfigError
from magail_sumo.sim.dynamics import BicycleLimits, limit_steer_rate
from magail_sumo.training.checkpoints import CheckpointError

SID = "637f20cafde22ff8"


def test_limit_clips_around_the_previous_angle_and_zero_is_no_limit():
    prev = np.array([0.0, 0.1, -0.2, 0.3])
    want = np.array([0.5, 0.1, -0.5, 0.28])
    got = limit_steer_rate(want, prev, BicycleLimits(max_steer_rate=0.3), 0.1)
    assert np.allclose(got, [0.03, 0.1, -0.23, 0.28])
    assert limit_steer_rate(want, prev, BicycleLimits(), 0.1) is want


def test_negative_or_infinite_rate_is_refused():
    from magail_sumo.config import from_dict
    from magail_sumo.env.config import EnvConfig

    for bad in (-0.1, float("inf")):
        with pytest.raises(ConfigError, match="limits.max_steer_rate"):
            from_dict(EnvConfig, {"limits": {"max_steer_rate": bad}})


@pytest.mark.sumo
def test_agents_steer_within_the_rate_and_observe_what_was_applied():
    """Random actions on a real scene: with the limit every agent's applied front-wheel angle
    (its previous action, which it observes) moves at most ``rate·dt`` a step, and its yaw
    follows that angle; without it the angles jump."""
    from converters import load_scene
    from magail_sumo.env import EnvConfig, SumoDrivingEnv

    scene = load_scene(WOMD_DIR / f"{SID}.tfrecord")
    rate, dt = 0.3, 0.1
    jumps = {}
    for r in (0.0, rate):
        lim = BicycleLimits(max_steer_rate=r)
        env = SumoDrivingEnv(scene, ROOT / "networks" / SID, EnvConfig(
            controlled="all", start_step=10, max_steps=20, terminate_on=(), sumo_mirror=False,
            limits=lim))
        try:
            env.reset(seed=0)
            rng = np.random.default_rng(0)
            rows = None
            prev = None
            worst = 0.0
            for _ in range(15):
                acts = {a: rng.uniform(-1, 1, 2).astype(np.float32) for a in env.agents}
                env.step(acts)
                if rows is None:
                    rows = np.flatnonzero(env.fleet.active)
                steer = env.fleet.prev_action[rows, 1] * lim.max_steer
                if prev is not None:
                    worst = max(worst, float(np.abs(steer - prev).max()))
                prev = steer
            jumps[r] = worst
        finally:
            env.close()
    assert jumps[rate] <= rate * dt + 1e-6
    assert jumps[0.0] > 10 * rate * dt


@pytest.mark.sumo
def test_checkpoint_brings_its_steering_rate_to_evaluation(tmp_path, env_configs):
    from converters import load_scene
    from magail_sumo import policies
    from magail_sumo.evaluation import methods

    ckpt = tiny_checkpoint(tmp_path / "rate.pt", {"limits": {"max_steer_rate": 0.3}})
    policy = policies.make_policy(str(ckpt), 0)
    assert policy.limits == BicycleLimits(max_steer_rate=0.3)
    scene = load_scene(WOMD_DIR / f"{SID}.tfrecord")
    methods.simulate(scene, str(ckpt), [0], seed=0, bundle_dir=ROOT / "networks" / SID)
    assert [c.limits.max_steer_rate for c in env_configs] == [0.3]
    # a checkpoint trained with other limits is still refused
    other = tiny_checkpoint(tmp_path / "steer.pt", {"limits": {"max_steer": 0.5}})
    with pytest.raises(CheckpointError, match="max_steer: trained 0.5, evaluation 0.7"):
        policies.make_policy(str(other), 0)
