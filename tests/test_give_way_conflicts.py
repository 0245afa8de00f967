"""Giving way inside a junction only to road users in the agent's way
(``ObservationConfig.give_way_conflicts``): on cologne8's signal ``26110729`` a left turn
waiting inside the junction read every vehicle on the oncoming lane and on the waiting place's
foe internal lanes, the right turners onto the lane beside its own and the oncoming left
turners among them, which SUMO's own drivers go past (issue 32)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from conftest import ROOT

COLOGNE8 = ROOT / "data" / "sumo" / "cologne8" / "cologne8.sumocfg"
#: the left turn of the single-lane approach -42925825#2: its first internal lane and the one
#: it waits at (an internal junction), oncoming right turn, oncoming straight, and the straight
#: connection from the cross street onto the left turn's own lane
LEFT, WAIT, RIGHT, STRAIGHT, SAME = (":26110729_2_0", ":26110729_18_0", ":26110729_9_0",
                                    ":26110729_10_0", ":26110729_14_1")


def _idm_city(steps: int, conflicts: bool):
    from magail_sumo.agents import env_settings
    from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv
    from magail_sumo.env.config import EnvConfig
    from magail_sumo.policies import make_policy

    pol = make_policy("idm", 0)
    settings = env_settings(pol)
    settings["observation"] = replace(settings["observation"], give_way_conflicts=conflicts)
    cfg = CityEnvConfig.from_env(EnvConfig(**settings), max_agents=200, control_fraction=1.0,
                                 warmup_s=600, max_steps=steps)
    return pol, SumoCityEnv(COLOGNE8, cfg)


@pytest.mark.sumo
def test_inside_a_junction_only_road_users_in_the_agents_way_are_given_way_to():
    """With ``give_way_conflicts`` the connections in the way of the waiting left turn are the
    crossing oncoming straight one and the one onto its own lane, not the oncoming right turn
    onto the lane beside it; in 3 min of IDM agents the give-way time read for agents inside a
    junction is never shorter than without it (it only leaves road users out) and longer for
    agents standing in the left turn (without the change both read alike)."""
    pol, env = _idm_city(1800, conflicts=True)
    on_ob = env.config.observation
    off_ob = replace(on_ob, give_way_conflicts=False)
    shorter = longer = inside = 0
    try:
        obs, _ = env.reset(seed=0)
        assert env._conflicting(WAIT, STRAIGHT) and env._conflicting(WAIT, SAME)
        assert not env._conflicting(WAIT, RIGHT)
        api = env._session.api
        for t in range(1800):
            obs, *_ = env.step(pol.act(obs))
            if t % 5:
                continue
            live = env.fleet.live()
            on = env._give_way(live)
            env.config = replace(env.config, observation=off_ob)
            try:
                off = env._give_way(live)
            finally:
                env.config = replace(env.config, observation=on_ob)
            for i, name in enumerate(env.fleet.names_of(live)):
                if not api.vehicle.getLaneID(name).startswith(":"):
                    continue
                inside += 1
                shorter += bool(on[i, 1] < off[i, 1] - 1e-9)
                longer += bool(api.vehicle.getLaneID(name) == LEFT and on[i, 1] > off[i, 1])
    finally:
        env.close()
    assert inside >= 50 and shorter == 0 and longer >= 3, (inside, shorter, longer)
