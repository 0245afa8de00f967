"""Route look-ahead observation (``observation.route_points``): the recorded route ahead of each
agent in its ego frame, in the env, the expert data and evaluation."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR, tiny_checkpoint
from magail_sumo.sensors.command import RouteCommands
from magail_sumo.sensors.observation import ObservationConfig, observation_names

SID = "637f20cafde22ff8"
POINTS = (10.0, 20.0, 30.0)


def _line_routes() -> RouteCommands:
    """One track along +x: states at x = 0, 1, 2, (invalid), 4, 5, then invalid to the end."""
    x = np.array([[0.0, 1.0, 2.0, 99.0, 4.0, 5.0, 99.0]])
    valid = np.array([[True, True, True, False, True, True, False]])
    tracks = SimpleNamespace(valid=valid, x=x, y=np.zeros_like(x), heading=np.zeros_like(x))
    return RouteCommands.build(tracks)


def test_route_ahead_interpolates_along_the_route_and_stops_at_its_end():
    r = _line_routes()
    # an agent near the state x=1, 0.5 m left of the route, heading +x
    got = r.ahead(np.array([0]), np.array([1.1]), np.array([0.5]), np.array([0.0]),
                  (2.0, 10.0))
    # 2 m on from x=1: x=3 (the gap runs straight from x=2 to x=4); 10 m on: the end, x=5
    assert np.allclose(got, [[3.0 - 1.1, -0.5, 5.0 - 1.1, -0.5]], atol=1e-6)
    # the same agent heading +y: the route ahead lies to its right
    got = r.ahead(np.array([0]), np.array([1.1]), np.array([0.5]), np.array([np.pi / 2]),
                  (2.0,))
    assert np.allclose(got, [[-0.5, -(3.0 - 1.1)]], atol=1e-6)
    assert r.ahead(np.array([], np.int64), np.array([]), np.array([]), np.array([]),
                   POINTS).shape == (0, 6)


def test_route_points_names_and_refusals():
    names = observation_names(ObservationConfig(route_points=(5.0, 12.5)))
    assert names[-4:] == ["route_x_5", "route_y_5", "route_x_12p5", "route_y_12p5"]
    assert len(names) == len(observation_names()) + 4
    for bad in ((10.0, 10.0), (0.0,), (float("nan"),)):
        with pytest.raises(ValueError, match="route_points"):
            ObservationConfig(route_points=bad)


@pytest.mark.sumo
def test_env_observes_the_recorded_route_ahead():
    """At the log's states (step 10 of a real scene) every agent's route point ``d`` m ahead is
    at most ``d`` m away (a route is never shorter than the straight line), and the moving
    vehicles see it ahead of them."""
    from converters import load_scene
    from magail_sumo.env import EnvConfig, SumoDrivingEnv

    scene = load_scene(WOMD_DIR / f"{SID}.tfrecord")
    cfg = EnvConfig(controlled="all", start_step=10, max_steps=5,
                    observation=ObservationConfig(route_points=POINTS))
    env = SumoDrivingEnv(scene, ROOT / "networks" / SID, cfg)
    try:
        obs, _ = env.reset(seed=0)
        names = observation_names(cfg.observation)
        cols = [names.index(f"route_{a}_{d:g}") for d in POINTS for a in "xy"]
        pts = np.stack([obs[a][cols] for a in sorted(obs)]).reshape(len(obs), len(POINTS), 2)
        assert np.all(np.linalg.norm(pts, axis=2) <= np.array(POINTS)[None] + 1e-3)
        speed = np.array([obs[a][names.index("speed")] for a in sorted(obs)])
        moving = speed > 5.0
        assert moving.sum() >= 3
        # mostly straight ahead (a turn or a track ending sooner brings some nearer)
        assert np.median(pts[moving, 0, 0]) > 9.0 and np.mean(pts[moving, 0, 0] > 5.0) > 0.8
        # stepping on keeps the feature consistent with the agents' own poses
        obs, *_ = env.step({a: np.zeros(2, np.float32) for a in env.agents})
        assert all(np.isfinite(o[cols]).all() for o in obs.values())
    finally:
        env.close()


def _route_checkpoint(tmp_path):
    return tiny_checkpoint(tmp_path / "route.pt", {"observation": {"route_points": list(POINTS)}})


@pytest.mark.sumo
def test_checkpoint_brings_its_route_points_to_evaluation(tmp_path):
    """A policy trained with the route look-ahead is evaluated in an env that computes it (the
    policy's ``observation``); other observation changes are still refused."""
    from converters import load_scene
    from magail_sumo import policies
    from magail_sumo.env import EnvConfig
    from magail_sumo.evaluation import methods
    from magail_sumo.policies import load_checkpoint_policy
    from magail_sumo.training.trainer import CheckpointError

    ckpt = _route_checkpoint(tmp_path)
    policy = policies.make_policy(str(ckpt), 0)
    assert policy.observation.route_points == POINTS
    assert policy.obs_dim == len(observation_names()) + 2 * len(POINTS)
    with pytest.raises(CheckpointError, match="env.observation.route_points"):
        load_checkpoint_policy(ckpt, target=EnvConfig())
    scene = load_scene(WOMD_DIR / f"{SID}.tfrecord")
    ro = methods.simulate(scene, str(ckpt), [0], seed=0, bundle_dir=ROOT / "networks" / SID)
    assert np.isfinite(ro.x).any()
