"""The shape of a sampling policy's noise (``magail_sumo.agents.noise``): per-action weights and
step-to-step correlation, from a pretrained card through evaluation."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from conftest import tiny_checkpoint
from magail_sumo import policies, pretrained
from magail_sumo.agents import PolicyError
from magail_sumo.agents.noise import NoiseProcess, NoiseShape


def test_correlated_noise_keeps_its_marginal_and_has_the_asked_correlation():
    """e_t = rho e_{t-1} + sqrt(1 - rho²) xi_t: every step N(0, 1) per action, lag-j
    correlation rho^j, each agent its own process; weights scale each action."""
    shape = NoiseShape(weights=(1.0, 0.5), correlation=(0.8, 0.3))
    proc = NoiseProcess(shape)
    rng = np.random.default_rng(0)
    n, steps = 4000, 12
    out = np.stack([proc(rng.standard_normal((n, 2)), np.arange(n)) for _ in range(steps)])
    assert out.shape == (steps, n, 2)
    std = out.reshape(-1, 2).std(0)
    assert np.allclose(std, [1.0, 0.5], atol=0.02)
    for j in (1, 2):
        corr = [np.corrcoef(out[j:, :, d].ravel(), out[:-j, :, d].ravel())[0, 1] for d in (0, 1)]
        assert np.allclose(corr, [0.8 ** j, 0.3 ** j], atol=0.02)


def test_agents_are_keyed_and_reset_starts_afresh():
    """An agent's noise depends on its own past only: the same draws in another order of keys
    give the same per-agent values; a new key starts from its draw; reset forgets."""
    proc = NoiseProcess(NoiseShape(correlation=(0.9, 0.9)))
    xi = np.arange(6.0).reshape(3, 2)
    first = proc(xi, np.array([0, 1, 2]))
    assert np.array_equal(first, xi)  # nobody has a past: the draws themselves
    again = proc(xi[::-1], np.array([2, 1, 0]))[::-1]
    keep = np.sqrt(1 - 0.81)
    assert np.allclose(again, 0.9 * xi + keep * xi)
    assert np.array_equal(proc(xi[:1], np.array([7])), xi[:1])  # a new agent
    proc.reset()
    assert np.array_equal(proc(xi, np.array([0, 1, 2])), xi)
    assert list(NoiseProcess(NoiseShape()).key(["b", "a", "b", "c"])) == [0, 1, 0, 2]
    with pytest.raises(ValueError, match="needs the agents' keys"):
        proc(xi, None)


def test_white_unit_noise_is_the_draws_and_bad_shapes_are_refused():
    plain = NoiseProcess(NoiseShape())
    xi = np.random.default_rng(1).standard_normal((5, 2))
    assert np.array_equal(plain(xi, None), xi) and NoiseShape().plain
    assert not NoiseShape(weights=(1.0, 0.5)).plain and NoiseShape(weights=(1.0, 0.5)).white
    for kw, msg in ((dict(correlation=(1.0, 0.0)), "correlation must be 2 numbers in \\[0, 1\\)"),
                    (dict(correlation=(0.5,)), "correlation must be 2 numbers"),
                    (dict(weights=(-1.0, 1.0)), "weights must be 2 numbers >= 0"),
                    (dict(weights=("a", 1.0)), "weights must be 2 numbers >= 0"),
                    (dict(weights=(float("nan"), 1.0)), "weights must be 2 numbers >= 0")):
        with pytest.raises(PolicyError, match=msg):
            NoiseShape(**kw)


def test_a_card_gives_the_shape_and_a_checkpoint_policy_samples_with_it(tmp_path, monkeypatch):
    """A card's ``noise_weights`` / ``noise_correlation`` reach the policy (kept when
    ``--noise-scale`` overrides the scale); its actions are ``tanh(mu + k·sigma·w⊙e_t)`` with
    e_t the correlated process of the policy's own draws; a policy without sampling noise
    refuses a shape, and an export refuses a shape without a scale."""
    ckpt = tiny_checkpoint(tmp_path / "agent.pt", {})
    reg = tmp_path / "registry"
    shape = NoiseShape(weights=(1.0, 0.5), correlation=(0.7, 0.5))
    pretrained.export(ckpt, "smooth", reg, noise_scale=0.5, noise_note="test",
                      noise_shape=shape)
    card = json.loads((reg / "smooth.json").read_text())
    assert card["sampling"]["noise_weights"] == [1.0, 0.5]
    assert card["sampling"]["noise_correlation"] == [0.7, 0.5]
    with pytest.raises(pretrained.PretrainedError, match="needs its noise scale"):
        pretrained.export(ckpt, "noscale", reg, noise_shape=shape)
    monkeypatch.setenv(pretrained.ENV_VAR, str(reg))
    pol = policies.make_policy("pretrained:smooth", seed=3)
    assert pol.noise_shape == shape and pol.noise_scale == 0.5
    over = policies.make_policy("pretrained:smooth", seed=3, noise_scale=1.0)
    assert over.noise_shape == shape and over.noise_scale == 1.0

    rng = np.random.default_rng(2)
    obs = [{str(k): rng.normal(size=pol.obs_dim).astype(np.float32) for k in range(4)}
           for _ in range(3)]
    got = [pol.act(o) for o in obs]
    # the same by hand: the policy's generator, sorted names, the AR(1) recursion
    det = policies.make_policy(str(ckpt), seed=0)
    gen = torch.Generator().manual_seed(3)
    prev = None
    rho, w = np.array([0.7, 0.5]), np.array([1.0, 0.5])
    for o, g in zip(obs, got):
        names = sorted(o)
        x = torch.as_tensor(np.stack([o[n] for n in names]))
        with torch.no_grad():
            dist = det.policy.get_distribution(x).distribution
            xi = torch.randn(dist.mean.shape, generator=gen).numpy().astype(np.float64)
            e = xi if prev is None else rho * prev + np.sqrt(1 - rho ** 2) * xi
            prev = e
            want = torch.tanh(dist.mean + 0.5 * dist.stddev * torch.as_tensor(e * w).float())
        assert np.allclose(np.stack([g[n] for n in names]), want.numpy(), atol=1e-6)

    # the batched path draws and remembers the same way (fleet rows as keys)
    pol.reseed_worlds([3])
    rows = np.array([10, 11, 12, 13])
    for o, g in zip(obs, got):
        x = np.stack([o[n] for n in sorted(o)])
        a = pol.act_batch(x, np.zeros(4, np.int64), rows)
        assert np.array_equal(a, np.stack([g[n] for n in sorted(o)]))
    pol.reseed_worlds([3])
    with pytest.raises(ValueError, match="needs act_batch's agents"):
        pol.act_batch(x, np.zeros(4, np.int64))
    with pytest.raises(PolicyError, match="RandomPolicy has no sampling noise to shape"):
        policies.registry._shaped("random", policies.make_policy("random", 0), shape)


@pytest.mark.parametrize("prior", ["none", "idm"])
def test_the_actor_gaussian_is_the_distributions_mean_and_std_bit_for_bit(prior):
    """``actor_gaussian`` (evaluation's fast path) gives what SB3's distribution object gives,
    with and without an action prior."""
    from magail_sumo.config import from_dict
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.trainer import make_policy

    env = {"action_layout": "accel_offset", "observation": {"leader": True, "light_gap": True}} \
        if prior == "idm" else {}
    cfg = from_dict(TrainConfig, {"seed": 1, "env": env, "policy": {
        "actor_hidden": [16, 16], "critic_hidden": [8], "action_prior": prior}})
    torch.manual_seed(1)
    policy = make_policy(cfg)
    with torch.no_grad():
        policy.log_std.add_(torch.tensor([0.3, -0.2]))
        obs = torch.as_tensor(np.random.default_rng(0).uniform(
            -1, 1, (23, policy.observation_space.shape[0])).astype(np.float32))
        mean, std = policy.actor_gaussian(obs)
        dist = policy.get_distribution(obs).distribution
    assert torch.equal(mean, dist.mean) and torch.equal(std, dist.stddev)


def test_a_batch_of_worlds_acts_as_each_world_alone_with_correlated_noise(tmp_path, monkeypatch):
    """``act_batch`` over three worlds of uneven sizes, correlated noise, several steps: world
    ``w``'s actions are bit for bit those of a policy reseeded with its seed acting on its
    rows alone."""
    ckpt = tiny_checkpoint(tmp_path / "agent.pt", {})
    reg = tmp_path / "registry"
    pretrained.export(ckpt, "smooth", reg, noise_scale=0.7, noise_note="test",
                      noise_shape=NoiseShape(weights=(1.0, 0.5), correlation=(0.6, 0.3)))
    monkeypatch.setenv(pretrained.ENV_VAR, str(reg))
    batch = policies.make_policy("pretrained:smooth", seed=0)
    seeds, sizes = [5, 9, 2], [3, 1, 4]
    batch.reseed_worlds(seeds)
    alone = [policies.make_policy("pretrained:smooth", seed=s) for s in seeds]
    worlds = np.repeat(np.arange(3), sizes)
    rows = np.arange(worlds.size) + 100
    rng = np.random.default_rng(4)
    for _ in range(3):
        x = rng.normal(size=(worlds.size, batch.obs_dim)).astype(np.float32)
        got = batch.act_batch(x, worlds, rows)
        for w, pol in enumerate(alone):
            names = [f"v{r}" for r in rows[worlds == w]]  # sorted as act sorts them
            want = pol.act(dict(zip(names, x[worlds == w])))
            assert np.array_equal(got[worlds == w], np.stack([want[n] for n in names]))
