"""The stop-line distance sensor (``observation.light_gap``) on real recorded scenes and in a
real SUMO city, the give-way sensor (``observation.give_way``) in a real city, and the action
prior (``policy.action_prior: idm``): an untrained actor drives
like the IDM rule, its log-probabilities are those of the Gaussian centred on the prior, and a
checkpoint brings the prior back in evaluation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import ROOT, SCENARIONET_DIR, WOMD_DIR, tiny_checkpoint
from converters import load_scene
from magail_sumo.config import ConfigError, from_dict
from magail_sumo.models.idm import IdmRule
from magail_sumo.models.priors import PRIOR_CLIP
from magail_sumo.sensors.observation import (
    Boxes, EgoState, ObservationConfig, SensorSuite, observation_names,
)
from magail_sumo.sensors.traffic_lights import LightTable
from magail_sumo.sensors.units.light_gap import LIGHT_RANGE
from magail_sumo.training.config import TrainConfig
from magail_sumo.training.policies import make_policy

OBS = {"leader": True, "light_gap": True, "route_points": [10.0, 20.0, 40.0]}
PRIOR_ENV = {"action_layout": "accel_offset", "observation": OBS}


def _log_observations(path, every: int = 5):
    """(rows, speed) of every recorded vehicle every ``every`` log steps, observed with the
    stop-line distance."""
    scene = load_scene(path)
    cfg = ObservationConfig(light_gap=True)
    suite = SensorSuite(scene, cfg)
    names = observation_names(cfg)
    tr, rows, speed = scene.tracks, [], []
    for t in range(0, scene.num_steps, every):
        idx = np.flatnonzero(tr.valid[:, t])
        v = np.hypot(tr.vx[idx, t], tr.vy[idx, t]).astype(np.float64)
        boxes = Boxes(tr.x[idx, t], tr.y[idx, t], tr.heading[idx, t].astype(np.float64),
                      tr.length[idx, t], tr.width[idx, t], v)
        ego = EgoState(np.arange(idx.size), v, np.zeros((idx.size, 2)),
                       np.zeros((idx.size, 2)), np.zeros(idx.size))
        rows.append(suite.observe(boxes, ego, t))
        speed.append(v)
    return np.concatenate(rows), np.concatenate(speed), names, scene


@pytest.mark.parametrize("path", [WOMD_DIR / "637f20cafde22ff8.tfrecord",
                                  SCENARIONET_DIR / "7b24d74b506c94ce.pkl"],
                         ids=lambda p: p.stem)
def test_stop_line_distance_of_recorded_drivers_waiting_at_red(path):
    """Recorded vehicles standing at a red light see its stop line a few metres ahead (the
    first of a queue within 5 m), never beyond the range; with no light the sensor reads its
    range; every value lies within the declared bounds."""
    obs, speed, names, scene = _log_observations(path)
    light, gap = obs[:, names.index("light")], obs[:, names.index("light_gap")]
    assert ((gap >= 0) & (gap <= LIGHT_RANGE)).all()
    assert (gap[light == 0] == LIGHT_RANGE).all()
    waiting = (light == 3) & (speed < 0.5) & (gap < LIGHT_RANGE)
    assert waiting.sum() >= 5, "the scene has vehicles waiting at a red light"
    assert gap[waiting].min() < 5.0 and np.median(gap[waiting]) < 25.0
    table = LightTable.build(scene)
    assert table.inherited is not None and table.inherited.any()
    own = np.flatnonzero(~table.inherited & (table.codes > 0).any(axis=0))
    assert not table.at_end(own).any() and not table.at_end(np.array([-1])).any()


@pytest.mark.sumo
def test_city_stop_line_distance_is_sumo_next_signal():
    """In a SUMO city the sensor reads SUMO's distance to each agent's next signal
    (``getNextTLS``), capped at the range, and the range where the light reads none."""
    from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv

    cfg = CityEnvConfig(observation=ObservationConfig(**OBS), action_layout="accel_offset",
                        max_agents=100, warmup_s=300, max_steps=50)
    env = SumoCityEnv(ROOT / "data" / "sumo" / "cologne8" / "cologne8.sumocfg", cfg)
    names = observation_names(cfg.observation)
    near = 0
    try:
        obs, _ = env.reset(seed=0)
        vehicle = env._session.api.vehicle
        for step in range(40):
            obs, *_ = env.step({a: np.array([0.2, 0.0], np.float32) for a in obs})
            for agent, row in obs.items() if step % 5 == 4 else ():
                nxt = vehicle.getNextTLS(agent)
                want = min(nxt[0][2], LIGHT_RANGE) if nxt else LIGHT_RANGE
                if row[names.index("light")] == 0:
                    want = LIGHT_RANGE
                assert row[names.index("light_gap")] == pytest.approx(want, abs=1e-3), agent
                near += want < LIGHT_RANGE
    finally:
        env.close()
    assert near >= 3, "some agents have a signal within range"


@pytest.mark.sumo
def test_city_give_way_conflict_is_a_sumo_junction_foe():
    """In a SUMO city the give-way features name a conflict SUMO's junction model has: a foe
    the agent must respond to, the agent's distance to the conflict, and the foe's time to it
    at its speed; none (the caps) otherwise."""
    from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv
    from magail_sumo.sensors.units.give_way import (COMMITTED, GIVE_WAY_HORIZON,
                                                   GIVE_WAY_RANGE)

    cfg = CityEnvConfig(observation=ObservationConfig(**OBS, give_way=True),
                        action_layout="accel_offset", max_agents=100, warmup_s=600,
                        max_steps=60)
    env = SumoCityEnv(ROOT / "data" / "sumo" / "cologne8" / "cologne8.sumocfg", cfg)
    names = observation_names(cfg.observation)
    gi, ti = names.index("give_way_gap"), names.index("give_way_time")
    seen = matched = 0
    try:
        obs, _ = env.reset(seed=0)
        vehicle = env._session.api.vehicle
        for step in range(60):
            obs, _, term, trunc, _ = env.step({a: np.array([0.1, 0.0], np.float32)
                                               for a in obs})
            speed = dict(zip(env._sumo.ids, env._sumo.speed))
            for agent, row in obs.items():
                if term[agent] or trunc[agent]:  # taken out of SUMO after this observation
                    continue
                gap, time = row[gi], row[ti]
                if gap == GIVE_WAY_RANGE or agent not in speed:  # none, or not in SUMO now
                    assert gap == GIVE_WAY_RANGE and time == GIVE_WAY_HORIZON
                    continue
                seen += 1
                foes = [(d, min(max(fd, 0) / max(speed[f], 0.1), GIVE_WAY_HORIZON))
                        for f, d, fd, _, fx, _, _, respond, _ in
                        vehicle.getJunctionFoes(agent, GIVE_WAY_RANGE)
                        if respond and d > COMMITTED and fx > 0]
                matched += any(d == pytest.approx(gap, abs=1e-3) and
                               t == pytest.approx(time, abs=1e-3) for d, t in foes)
    finally:
        env.close()
    assert seen >= 5, "some agents meet a junction conflict"
    # agents taken out at the end of a step leave SUMO after the others were observed: a
    # conflict with one of them is gone when the test asks SUMO again
    assert matched >= 0.8 * seen, (matched, seen)


def _prior_config(**policy) -> TrainConfig:
    return from_dict(TrainConfig, {"env": PRIOR_ENV, "policy": {"action_prior": "idm",
                                                               **policy}})


def _rows(names: list[str]) -> np.ndarray:
    obs = np.zeros((4, len(names)), np.float32)
    obs[:, names.index("speed")] = [0.0, 8.0, 10.0, 12.0]
    obs[:, names.index("leader_gap")] = [50.0, 50.0, 6.0, 50.0]
    obs[:, names.index("light")] = [0, 0, 0, 3]
    obs[:, names.index("light_gap")] = [50.0, 50.0, 50.0, 20.0]
    for d in (10, 20, 40):
        obs[:, names.index(f"route_x_{d}")] = d
    return obs


def test_untrained_actor_with_the_idm_prior_drives_like_the_rule():
    """An untrained actor's deterministic action is the IDM rule's (its last layer starts near
    0); the log-probability PPO evaluates is the forward pass's; without the prior the same
    actor is centred near 0."""
    cfg = _prior_config()
    names = observation_names(cfg.env.observation)
    obs = torch.as_tensor(_rows(names))
    rule = IdmRule(cfg.env.observation, cfg.env.limits)(obs.numpy())
    torch.manual_seed(0)
    policy = make_policy(cfg)
    with torch.no_grad():
        act = policy._predict(obs, deterministic=True).numpy()
        assert np.abs(act - np.clip(rule, -PRIOR_CLIP, PRIOR_CLIP)).max() < 0.05
        assert act[2, 0] < -0.3 and act[3, 0] < -0.3 and act[0, 0] > 0.1
        sampled, _, log_prob = policy.forward(obs)
        _, again, _ = policy.evaluate_actions(obs, sampled)
        assert torch.allclose(again, log_prob, atol=1e-5)
    plain = make_policy(from_dict(TrainConfig, {"env": PRIOR_ENV}))
    with torch.no_grad():
        assert np.abs(plain._predict(obs, deterministic=True).numpy()).max() < 0.05


def test_checkpoint_brings_the_prior_back(tmp_path):
    """A checkpoint trained with the prior acts with it in evaluation (the policy is rebuilt
    from the run's config)."""
    from magail_sumo.policies import load_checkpoint_policy

    path = tiny_checkpoint(tmp_path / "prior.pt", PRIOR_ENV)
    # the tiny checkpoint has no prior: write one with it
    state = torch.load(path, weights_only=True)
    state["config"]["policy"]["action_prior"] = "idm"
    torch.save(state, path)
    pol = load_checkpoint_policy(path, seed=0, deterministic=True)
    names = observation_names(ObservationConfig(**OBS))
    rows = _rows(names)
    act = pol.act({str(i): r for i, r in enumerate(rows)})
    got = np.stack([act[str(i)] for i in range(len(rows))])
    assert got[2, 0] < -0.3 and got[0, 0] > 0.1


@pytest.mark.parametrize("settings, problem", [
    ({"env": {"observation": OBS}, "policy": {"action_prior": "idm"}}, "accel_offset"),
    ({"env": {"action_layout": "accel_offset"}, "policy": {"action_prior": "idm"}},
     "light_gap"),
    ({"policy": {"action_prior": "pid"}}, "must be one of none, idm"),
    ({"algorithm": "sac_gail", "env": {**PRIOR_ENV, "observation": {**OBS, "command": True}},
      "policy": {"action_prior": "idm"}}, "PPO-family"),
])
def test_bad_prior_settings_are_one_line(settings, problem):
    with pytest.raises(ConfigError, match=problem) as err:
        from_dict(TrainConfig, settings)
    assert "policy.action_prior" in str(err.value) or "action_prior" in str(err.value)


BRISK = {"a_lat": 4.0, "a_clear": 2.0, "margin": 0.5}
BRISK_CONFIG = ROOT / "configs" / "experiments" / "city" / "route_idm_path_leader_brisk.yaml"


def _bend_rows(names: list[str]) -> np.ndarray:
    """:func:`_rows` plus a car at 8 m/s before a bend of about 13 m radius (the default bend
    speed, ``sqrt(2 / κ)``, is under 8 m/s; at 4 m/s² it is over) and one 15 m from a junction
    conflict whose foe is 2.2 s away (a gap refused with the defaults, clearing at 1.5 m/s²
    with a 1-s margin; accepted at 2.0 m/s² with 0.5 s)."""
    obs = np.zeros((6, len(names)), np.float32)
    obs[:4] = _rows(names)
    obs[4:, names.index("speed")] = 8.0
    obs[4:, names.index("leader_gap")] = 50.0
    obs[4:, names.index("light_gap")] = 50.0
    for d in (10, 20, 40):
        obs[4:, names.index(f"route_x_{d}")] = d
    obs[4, names.index("route_y_20")] = 15.0
    if "give_way_gap" in names:
        obs[:, names.index("give_way_gap")] = 50.0
        obs[:, names.index("give_way_time")] = 10.0
        obs[5, names.index("give_way_gap")] = 5.0
        obs[5, names.index("give_way_time")] = 2.2
    return obs


def test_prior_params_reach_the_rule_and_survive_a_checkpoint(tmp_path):
    """``policy.prior_params`` (here the brisk variant config's) sets the IDM prior's
    parameters: an untrained actor drives like the rule with them, not like the default rule;
    a checkpoint carries them into evaluation; a checkpoint from before the key loads with
    the defaults."""
    from dataclasses import replace

    from magail_sumo.config import load_config, to_dict
    from magail_sumo.models.idm import IdmParams
    from magail_sumo.policies import load_checkpoint_policy
    from magail_sumo.training.policies import load_policy
    from magail_sumo.training.trainer import CHECKPOINT_FORMAT

    variant = load_config(BRISK_CONFIG, TrainConfig)
    assert variant.policy.action_prior == "idm" and variant.policy.prior_params == BRISK
    obs_cfg = ObservationConfig(**OBS, give_way=True)
    cfg = from_dict(TrainConfig, {"seed": 1, "env": {**PRIOR_ENV, "observation": {
        **OBS, "give_way": True}}, "policy": {**to_dict(variant.policy), "actor_hidden": [8],
                                               "critic_hidden": [8]}})
    rows = _bend_rows(observation_names(obs_cfg))
    brisk = IdmRule(obs_cfg, cfg.env.limits, replace(IdmParams(), **BRISK))(rows)
    default = IdmRule(obs_cfg, cfg.env.limits)(rows)
    assert brisk[4, 0] > default[4, 0] + 0.1 and brisk[5, 0] > default[5, 0] + 0.1
    assert np.abs(brisk[:4] - default[:4]).max() < 1e-6  # straight, no conflict: the same

    def acts(policy) -> np.ndarray:
        with torch.no_grad():
            return policy._predict(torch.as_tensor(rows), deterministic=True).numpy()

    torch.manual_seed(1)
    policy = make_policy(cfg)
    assert policy.action_prior.params == replace(IdmParams(), **BRISK)
    assert np.abs(acts(policy) - np.clip(brisk, -PRIOR_CLIP, PRIOR_CLIP)).max() < 0.05

    path = tmp_path / "brisk.pt"
    torch.save({"format": CHECKPOINT_FORMAT, "update": 0, "config": to_dict(cfg),
                "policy": policy.state_dict()}, path)
    loaded, loaded_cfg = load_policy(path)
    assert loaded_cfg.policy.prior_params == BRISK
    assert np.abs(acts(loaded) - acts(policy)).max() < 1e-6
    pol = load_checkpoint_policy(path, seed=0, deterministic=True)  # what evaluate loads
    act = pol.act({str(i): r for i, r in enumerate(rows)})
    got = np.stack([act[str(i)] for i in range(len(rows))])
    assert np.abs(got - acts(policy)).max() < 1e-5

    state = torch.load(path, weights_only=True)  # a checkpoint from before the key
    del state["config"]["policy"]["prior_params"]
    torch.save(state, path)
    old, old_cfg = load_policy(path)
    assert old_cfg.policy.prior_params == {} and old.action_prior.params == IdmParams()
    assert np.abs(acts(old) - np.clip(default, -PRIOR_CLIP, PRIOR_CLIP)).max() < 0.05


@pytest.mark.parametrize("policy, problem", [
    ({"action_prior": "idm", "prior_params": {"a_lta": 4.0}},
     "unknown idm prior parameter 'a_lta' \\(known: v0, .*a_lat, .*margin\\)"),
    ({"action_prior": "idm", "prior_params": {"margin": -0.5}}, "finite number >= 0"),
    ({"prior_params": {"a_lat": 4.0}}, "needs policy.action_prior"),
])
def test_bad_prior_params_are_one_line(policy, problem):
    with pytest.raises(ConfigError, match=problem) as err:
        from_dict(TrainConfig, {"env": PRIOR_ENV, "policy": policy})
    assert "policy.prior_params" in str(err.value) and "\n" not in str(err.value)


def test_make_prior_refuses_an_unknown_parameter():
    from magail_sumo.models.priors import make_prior
    from magail_sumo.sim.dynamics import BicycleLimits

    with pytest.raises(ValueError, match="unknown idm prior parameter 'speed' \\(known: v0"):
        make_prior("idm", ObservationConfig(**OBS), BicycleLimits(), "accel_offset",
                   {"speed": 1.0})
