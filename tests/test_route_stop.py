"""The route's standing end (``observation.route_stop``): how far along its recorded route a
driver who halts where its record ends has to go, in the env on a real scene, and the IDM rule
stopping there."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import SCENARIONET_DIR
from magail_sumo.models.idm import IdmRule
from magail_sumo.sensors.command import STANDING, RouteCommands
from magail_sumo.sensors.observation import ObservationConfig, observation_names
from magail_sumo.sensors.units.route_stop import ROUTE_STOP_RANGE

#: a real WOMD scene (womd14 test split) where several recorded drivers come to a halt and
#: stand until the record ends
SID = "49c341dce1f65cdb"
OBS = ObservationConfig(leader=True, light_gap=True, route_points=(10.0, 20.0, 40.0),
                        route_stop=True)


def _scene():
    from converters import load_scene

    return load_scene(SCENARIONET_DIR / f"{SID}.pkl")


def _end_speed(tracks) -> np.ndarray:
    last = tracks.valid.shape[1] - 1 - np.argmax(tracks.valid[:, ::-1], axis=1)
    n = np.arange(len(last))
    return np.hypot(tracks.vx[n, last], tracks.vy[n, last])


def test_standing_end_along_the_recorded_route():
    """At the recorded states, the distance to a standing end is the route's remaining arc
    (non-increasing, 0 at the end); a route whose driver is moving at its end has none."""
    tr = _scene().tracks
    routes = RouteCommands.build(tr)
    standing = tr.valid.any(axis=1) & (_end_speed(tr) < STANDING)
    moving = tr.valid.any(axis=1) & ~standing
    assert standing.sum() >= 5 and moving.sum() >= 3
    for r in np.flatnonzero(tr.valid.any(axis=1)):
        t = np.flatnonzero(tr.valid[r])
        got = routes.stop_ahead(np.full(t.size, r), tr.x[r, t], tr.y[r, t])
        if not standing[r]:
            assert np.isinf(got).all()
            continue
        assert got[-1] == 0.0 and (got >= 0).all()
        # the remaining arc from the state itself (a jittering standing car may project onto a
        # neighbouring state of the same place)
        assert np.allclose(got, routes.end_arc[r] - routes.farc[r, t], atol=1.0)


@pytest.mark.sumo
def test_env_observes_the_standing_end_and_the_rule_stops_there(bundled_networks):
    """In the env (log positions at step 185): the feature reads the remaining arc for drivers
    who halt at their route's end, the range for the others; the IDM rule brakes every agent
    within a few metres of its standing end, and agents that read the range are not held by
    it."""
    from magail_sumo.env import EnvConfig, SumoDrivingEnv

    scene = _scene()
    cfg = EnvConfig(controlled="all", start_step=185, max_steps=5, action_layout="accel_offset",
                    observation=OBS)
    env = SumoDrivingEnv(scene, bundled_networks.bundle(SID), cfg)
    try:
        obs, _ = env.reset(seed=0)
    finally:
        env.close()
    names = observation_names(OBS)
    agents = sorted(obs)
    rows = np.stack([obs[a] for a in agents])
    gap = rows[:, names.index("route_stop_gap")]
    assert ((gap >= 0) & (gap <= ROUTE_STOP_RANGE)).all()
    tr = scene.tracks
    ids = [str(i) for i in tr.id]
    standing = _end_speed(tr) < STANDING
    near = gap < ROUTE_STOP_RANGE
    assert near.sum() >= 3 and (~near).sum() >= 3
    for a, g in zip(agents, gap):
        if not standing[ids.index(a)]:
            assert g == ROUTE_STOP_RANGE, a
    rule = IdmRule(OBS)
    accel = rule.accel(rows)
    close = gap < 2.0
    assert close.any() and (accel[close] < 0).all()
    free = rows.copy()
    free[:, names.index("route_stop_gap")] = ROUTE_STOP_RANGE
    unheld = IdmRule(ObservationConfig(leader=True, light_gap=True,
                                       route_points=(10.0, 20.0, 40.0))).accel(
        np.delete(rows, names.index("route_stop_gap"), axis=1))
    assert np.allclose(rule.accel(free), unheld)
    assert (accel <= unheld + 1e-9).all()


def test_checkpoint_brings_the_standing_end_to_evaluation(tmp_path):
    """A policy trained with the feature (and the give-way reading) evaluates in an env that
    computes them."""
    from conftest import tiny_checkpoint
    from magail_sumo import policies

    ckpt = tiny_checkpoint(tmp_path / "stop.pt", {"observation": {
        "route_stop": True, "give_way": True, "give_way_conflicts": True}})
    policy = policies.make_policy(str(ckpt), 0)
    assert policy.observation.route_stop and policy.observation.give_way_conflicts
    assert policy.obs_dim == len(observation_names(policy.observation))
    assert observation_names(policy.observation)[-1] == "route_stop_gap"
