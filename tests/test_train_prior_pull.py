"""The pull toward the action prior (``ppo.prior_coef``): PPO updates with it keep the actor's
residual to the IDM rule smaller than the same updates without it, on the same rollout buffer
of a real recorded scene; it is logged; it is refused without a prior."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from conftest import WOMD_DIR
from magail_sumo.config import ConfigError, from_dict
from magail_sumo.expert import ExpertDataset, record_expert
from magail_sumo.env.scene_specs import scene_specs
from magail_sumo.sensors.observation import observation_names
from magail_sumo.training.config import TrainConfig
from magail_sumo.training.trainer import GailRun

SCENE = str(WOMD_DIR / "850c48d8bbfa008f.tfrecord")
PRIOR_ENV = {"action_layout": "accel_offset", "max_steps": 30,
             "observation": {"leader": True, "light_gap": True,
                             "route_points": [10.0, 20.0, 40.0]}}


@pytest.fixture(scope="module")
def filled(tmp_path_factory, bundled_networks):
    """A GailRun with the IDM prior after one real update (a filled rollout buffer), and the
    policy's state then."""
    root = tmp_path_factory.mktemp("prior_pull")
    nets = bundled_networks("850c48d8bbfa008f")
    base = {"env": PRIOR_ENV, "policy": {"action_prior": "idm"}}
    obs = from_dict(TrainConfig, base).env.observation
    record_expert(scene_specs([SCENE], nets), root / "expert", obs)
    cfg = from_dict(TrainConfig, {
        **base, "seed": 3, "expert_dir": str(root / "expert"), "out_dir": str(root / "runs"),
        "updates": 1, "scenes": {"files": [SCENE], "networks": str(nets)},
        "policy": {"action_prior": "idm", "actor_hidden": [16, 16], "critic_hidden": [16, 16]},
        "ppo": {"n_steps": 16, "batch_size": 16, "n_epochs": 2, "prior_coef": 1.0},
        "discriminator": {"epochs": 1, "batch_size": 8, "transformer": {
            "embed_dim": 16, "num_layers": 1, "num_heads": 2, "ff_dim": 32}}})
    expert = ExpertDataset(cfg.expert_dir, observation_names(cfg.env.observation))
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    run = GailRun(cfg, expert)
    run.policy.obs_normalizer.update(torch.as_tensor(expert.s))
    run.run_update()
    yield run, copy.deepcopy(run.model.policy.state_dict()), \
        copy.deepcopy(run.model.policy.optimizer.state_dict())
    run.close()


def _residual_sq(model) -> float:
    """Mean ½‖residual‖² of the actor over the agent-steps of the rollout buffer."""
    buf = model.rollout_buffer
    obs = torch.as_tensor(buf.observations.reshape(-1, buf.observations.shape[-1]))
    active = getattr(buf, "active_flat", None)
    if active is not None and active.shape[0] == obs.shape[0]:
        obs = obs[torch.as_tensor(active)]
    with torch.no_grad():
        return float(0.5 * model.policy.actor_residual(obs).square().sum(-1).mean())


@pytest.mark.sumo
def test_prior_pull_keeps_the_residual_small(filled):
    run, state, optim = filled
    m = run.model
    got = {}
    for coef in (0.0, 50.0):
        m.policy.load_state_dict(state)
        m.policy.optimizer.load_state_dict(copy.deepcopy(optim))
        m.prior_coef = coef
        m.set_learning_rate(3e-3)
        torch.manual_seed(0)
        np.random.seed(0)
        logged = []
        for _ in range(4):
            m.logger.dump()
            m.train()
            logged.append(m.logger.name_to_value.get("train/prior_loss"))
        got[coef] = (_residual_sq(m), logged)
    free, pulled = got[0.0], got[50.0]
    assert free[1] == [None] * 4
    assert all(v is not None and np.isfinite(v) for v in pulled[1])
    # the residual grows without the pull and stays a fraction of that with it
    assert pulled[0] < 0.5 * free[0], (pulled[0], free[0])
    # the actor with the prior: its mean is the rule's pre-tanh action plus the residual
    obs = torch.as_tensor(m.rollout_buffer.observations.reshape(
        -1, m.rollout_buffer.observations.shape[-1])[:64])
    with torch.no_grad():
        mean, _ = m.policy.actor_gaussian(obs)
        assert torch.allclose(mean - m.policy.actor_residual(obs), m.policy._prior_mean)


def test_prior_pull_without_a_prior_is_refused():
    with pytest.raises(ConfigError, match="ppo.prior_coef.*needs policy.action_prior"):
        from_dict(TrainConfig, {"ppo": {"prior_coef": 0.5}})
    with pytest.raises(ConfigError, match="prior_coef"):
        from_dict(TrainConfig, {"env": PRIOR_ENV, "policy": {"action_prior": "idm"},
                                "ppo": {"prior_coef": -1.0}})
