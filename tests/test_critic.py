"""Transformer critic: values from all vehicles of a scene step (real SUMO scenes), scene-step
PPO minibatches, a real training run with exact resume, strict config."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from gymnasium import spaces

from conftest import ROOT, WOMD_DIR
from magail_sumo.config import ConfigError, from_dict, load_config
from magail_sumo.env.config import EnvConfig
from magail_sumo.env.vec_env import MultiSceneVecEnv
from magail_sumo.env.scene_specs import scene_specs
from magail_sumo.expert import record_expert
from magail_sumo.models.critic import CriticTransformerConfig, scene_groups
from magail_sumo.models.policies import TanhGaussianPolicy, with_scene_groups
from magail_sumo.training.config import PolicyConfig, TrainConfig
from magail_sumo.policies import load_checkpoint_policy
from magail_sumo.training.gail.ppo import MaskedPPO, MaskedRolloutBuffer
from magail_sumo.training.trainer import load_checkpoint, load_policy, train

SCENE_A = str(WOMD_DIR / "2831b6fde0420b0d.tfrecord")  # 12 slots, 10 agents at reset
SCENE_B = str(WOMD_DIR / "850c48d8bbfa008f.tfrecord")  # 2 slots, 1 agent at reset
TINY = CriticTransformerConfig(embed_dim=16, num_layers=1, num_heads=2, ff_dim=32)


@pytest.fixture(scope="module")
def scenes(bundled_networks):
    """A MaskedPPO with a transformer-critic policy on two real scenes, after one env step;
    the policy's normaliser fitted on that observation."""
    nets = bundled_networks(Path(SCENE_A).stem, Path(SCENE_B).stem)
    venv = MultiSceneVecEnv(scene_specs([SCENE_A, SCENE_B], nets), EnvConfig(max_steps=20),
                            seed=0)
    try:
        torch.manual_seed(0)
        model = MaskedPPO(TanhGaussianPolicy, venv, n_steps=4, batch_size=4, seed=0,
                          policy_kwargs={"net_arch": {"pi": [16], "vf": []},
                                         "critic": "transformer", "critic_transformer": TINY})
        venv.reset()
        obs, _, _, _ = venv.step(np.zeros((venv.num_envs, 2), np.float32))
        model.policy.obs_normalizer.update(torch.as_tensor(obs[venv.slot_active]))
        model.policy.set_training_mode(False)
        yield model, venv, obs.copy(), venv.slot_active.copy()
    finally:
        venv.close()


def values(policy, obs: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Rollout-time values of one vector-env observation (mask: override the env's)."""
    src = policy._mask_source
    if mask is not None:
        policy.set_scene_layout(policy._slot_scene, lambda: mask)
    try:
        with torch.no_grad():
            return policy.predict_values(torch.as_tensor(obs)).numpy()[:, 0]
    finally:
        policy.set_scene_layout(policy._slot_scene, src)


@pytest.mark.sumo
def test_wiring_from_the_env(scenes):
    model, venv, obs, active = scenes
    a, b = venv.scene_slices
    # 12: with a vehicle standing on a lane the whole log, which the converter now puts in SUMO
    assert (a.stop - a.start, b.stop - b.start) == (12, 2)
    assert active[a].sum() >= 2 and active[b].sum() >= 1 and not active.all()
    pol = model.policy
    assert np.array_equal(pol._slot_scene, venv.slot_scene)
    assert np.array_equal(model.rollout_buffer.slot_scene, venv.slot_scene)
    group = pol.critic_groups(torch.as_tensor(obs)).numpy()
    assert np.array_equal(group, scene_groups(venv.slot_scene, venv.slot_active))
    # active slots of a scene share a group, scenes never share one; free slots: -1
    for s in (a, b):
        assert len(set(group[s][active[s]])) == 1
    assert set(group[a][active[a]]).isdisjoint(group[b][active[b]])
    assert np.all(group[~active] == -1) and np.all(group[active] >= 0)
    # the state dict holds the transformer, not SB3's value head
    keys = pol.state_dict().keys()
    assert any(k.startswith("critic.encoder.") for k in keys)
    assert not any(k.startswith("value_net.") for k in keys)


@pytest.mark.sumo
def test_values_need_the_scene_context(scenes):
    """Changing one vehicle changes the values of the others of its scene."""
    model, venv, obs, active = scenes
    a = venv.scene_slices[0]
    rows = np.flatnonzero(active[a]) + a.start
    v = values(model.policy, obs)
    other = obs.copy()
    other[rows[0]] = obs[rows[1]] + 1.0
    v2 = values(model.policy, other)
    assert np.abs(v2[rows[1:]] - v[rows[1:]]).max() > 1e-4


@pytest.mark.sumo
def test_permutation_equivariant_within_a_scene(scenes):
    model, venv, obs, active = scenes
    a = venv.scene_slices[0]
    v = values(model.policy, obs)
    perm = np.arange(len(obs))
    perm[a] = a.start + np.random.default_rng(0).permutation(a.stop - a.start)
    assert not np.array_equal(perm, np.arange(len(obs)))
    vp = values(model.policy, obs[perm], active[perm])
    np.testing.assert_allclose(vp, v[perm], atol=1e-5)
    # training path (groups attached to the rows): the same values, in any row order
    rows = np.flatnonzero(active)
    group = torch.as_tensor(scene_groups(venv.slot_scene, active)[rows])
    shuffle = np.random.default_rng(1).permutation(len(rows))
    x = with_scene_groups(torch.as_tensor(obs[rows][shuffle]), group[shuffle])
    acts = torch.zeros(len(rows), 2)
    vt, _, _ = model.policy.evaluate_actions(x, acts)
    np.testing.assert_allclose(vt.detach().numpy()[:, 0], v[rows][shuffle], atol=1e-5)


@pytest.mark.sumo
def test_free_slots_and_other_scenes_do_not_matter(scenes):
    model, venv, obs, active = scenes
    a, b = venv.scene_slices
    rng = np.random.default_rng(2)
    v = values(model.policy, obs)
    noisy = obs.copy()
    noisy[~active] = rng.normal(size=noisy[~active].shape) * 5
    vn = values(model.policy, noisy)
    np.testing.assert_allclose(vn[active], v[active], atol=1e-6)
    assert np.all(vn[~active] == 0) and np.all(v[~active] == 0)  # free slots: not evaluated
    # scene B's vehicles (their observations, or an extra one) leave scene A's values alone
    other = obs.copy()
    other[b] = obs[a][active[a]][:2] * 1.5
    more = active.copy()
    more[b] = True
    vb = values(model.policy, other, more)
    np.testing.assert_allclose(vb[a][active[a]], v[a][active[a]], atol=1e-6)
    assert np.abs(vb[b][active[b]] - v[b][active[b]]).max() > 1e-4


@pytest.mark.sumo
def test_terminal_observation_is_a_one_vehicle_scene(scenes):
    """SB3 bootstraps a truncated agent from ``predict_values`` of its terminal observation
    alone: a one-vehicle scene."""
    model, venv, obs, active = scenes
    row = int(np.flatnonzero(active)[0])
    pol = model.policy
    with torch.no_grad():
        alone = pol.predict_values(pol.obs_to_tensor(obs[row])[0])
        solo = np.zeros(len(obs), bool)
        solo[row] = True
        assert alone.shape == (1, 1) and torch.isfinite(alone).all()
    assert float(alone) == pytest.approx(values(pol, obs, solo)[row], abs=1e-5)
    with pytest.raises(ValueError, match="whole scene steps"):
        pol.evaluate_actions(torch.as_tensor(obs), torch.zeros(len(obs), 2))


def test_buffer_yields_whole_scene_steps():
    n_steps, slot_scene = 6, np.array([0, 0, 0, 1, 1, 2])
    rng = np.random.default_rng(3)
    masks = rng.random((n_steps, len(slot_scene))) < 0.6
    masks[2] = False
    buf = MaskedRolloutBuffer(n_steps, spaces.Box(-1, 1, (2,), np.float32),
                              spaces.Box(-1, 1, (2,), np.float32), n_envs=len(slot_scene))
    buf.slot_scene = slot_scene
    it = iter(masks)
    buf.mask_source = lambda: next(it)
    for t in range(n_steps):  # observation = (step, slot)
        obs = np.stack([np.full(len(slot_scene), t), np.arange(len(slot_scene))], 1)
        buf.add(obs, np.zeros((len(slot_scene), 2)), np.zeros(len(slot_scene)),
                np.zeros(len(slot_scene)), torch.zeros(len(slot_scene)),
                torch.zeros(len(slot_scene)))
    buf.compute_returns_and_advantage(torch.zeros(len(slot_scene)), np.zeros(len(slot_scene)))
    seen, sizes = [], []
    for batch in buf.get(5):
        o = batch.observations.numpy().astype(int)
        group = batch.observations.scene_groups.numpy()
        sizes.append(len(o))
        keys = {(t, slot_scene[s]) for t, s in o}
        assert len(keys) == group.max() + 1  # one group per (step, scene), numbered 0..G-1
        for g in range(group.max() + 1):
            (t, sc), = {(t, slot_scene[s]) for t, s in o[group == g]}
            want = {s for s in np.flatnonzero(masks[t]) if slot_scene[s] == sc}
            assert {s for _, s in o[group == g]} == want  # the whole scene step
        seen += [tuple(r) for r in o]
    assert sorted(seen) == sorted(zip(*np.nonzero(masks)))  # every active slot-step once
    # about batch_size agent-steps per minibatch (no step has more than 5 agents here)
    assert len(sizes) == -(-masks.sum() // 5) and all(0 < s < 10 for s in sizes)


def test_bad_critic_config_refused(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("policy:\n  critic: attention\n")
    with pytest.raises(ConfigError, match=r"policy\.critic: 'attention' is not one of"):
        load_config(bad, TrainConfig)
    bad.write_text("policy:\n  critic: transformer\n  critic_transformer:\n    depth: 2\n")
    with pytest.raises(ConfigError, match=r"policy\.critic_transformer\.depth: unknown key"):
        load_config(bad, TrainConfig)
    bad.write_text("policy:\n  critic_transformer:\n    embed_dim: 10\n    num_heads: 4\n")
    with pytest.raises(ConfigError, match=r"policy\.critic_transformer\.num_heads: must divide embed_dim \(10\)"):
        load_config(bad, TrainConfig)
    with pytest.raises(ValueError, match="critic: must be"):
        PolicyConfig(critic="gnn")
    tcritic = load_config(ROOT / "configs" / "experiments" / "womd3" / "magail_tcritic.yaml",
                          TrainConfig)
    assert tcritic.policy.critic == "transformer"


@pytest.fixture(scope="module")
def setup(tmp_path_factory, bundled_networks):
    root = tmp_path_factory.mktemp("tcritic")
    nets = bundled_networks(Path(SCENE_A).stem, Path(SCENE_B).stem)
    record_expert(scene_specs([SCENE_B], nets), root / "expert")
    cfg = from_dict(TrainConfig, {
        "seed": 5, "expert_dir": str(root / "expert"), "out_dir": str(root / "runs"),
        "updates": 2, "checkpoint_every": 1,
        "env": {"max_steps": 30},
        "scenes": {"files": [SCENE_A, SCENE_B], "networks": str(nets)},
        "policy": {"actor_hidden": [16, 16], "critic": "transformer", "critic_transformer": {
            "embed_dim": 16, "num_layers": 1, "num_heads": 2, "ff_dim": 32, "dropout": 0.1}},
        "ppo": {"n_steps": 8, "batch_size": 26, "n_epochs": 2},
        "discriminator": {"epochs": 2, "batch_size": 8, "transformer": {
            "embed_dim": 16, "num_layers": 1, "num_heads": 2, "ff_dim": 32}}})
    return root, cfg


@pytest.mark.sumo
def test_transformer_critic_training_resumes_exactly(setup):
    """A real run with the transformer critic writes checkpoints; 2 updates straight equal
    1 update + resume + 1 bit for bit (critic dropout on, so its RNG use is covered too)."""
    root, cfg = setup
    straight = train(cfg, run_dir=root / "straight", log=lambda s: None)
    half = train(replace(cfg, updates=1), run_dir=root / "split", log=lambda s: None)
    resumed = train(cfg, resume=half, log=lambda s: None)
    a = load_checkpoint(straight / "checkpoints" / "latest.pt")
    b = load_checkpoint(resumed / "checkpoints" / "latest.pt")
    assert a["update"] == b["update"] == 2
    assert (straight / "checkpoints" / "update_000001.pt").is_file()
    assert any(k.startswith("critic.encoder.") for k in a["policy"])
    for key in ("policy", "discriminator"):
        assert a[key].keys() == b[key].keys()
        for k in a[key]:
            assert torch.equal(a[key][k], b[key][k]), (key, k)
    sa, sb = a["policy_optimizer"]["state"], b["policy_optimizer"]["state"]
    assert sa.keys() == sb.keys()
    for k in sa:
        for n in sa[k]:
            assert torch.equal(torch.as_tensor(sa[k][n]), torch.as_tensor(sb[k][n])), (k, n)
    assert a["learning_rate"] == b["learning_rate"] and a["num_timesteps"] == b["num_timesteps"]
    # the critic learnt something (weights moved from the first checkpoint)
    first = load_checkpoint(straight / "checkpoints" / "update_000001.pt")["policy"]
    head = "critic.value_head.weight"
    assert not torch.equal(first[head], a["policy"][head])
    # evaluation loads the actor of a transformer-critic checkpoint
    policy, got = load_policy(straight / "checkpoints" / "latest.pt")
    assert got.policy.critic == "transformer" and policy.critic_kind == "transformer"
    pol = load_checkpoint_policy(straight / "checkpoints" / "latest.pt")
    acts = pol.act({"x": np.zeros(pol.obs_dim, np.float32), "y": np.ones(pol.obs_dim, np.float32)})
    assert set(acts) == {"x", "y"} and all(np.all(np.abs(v) <= 1) for v in acts.values())


def test_bucketed_padding_equals_each_scene_alone():
    """Groups padded in size buckets give each group's values as if evaluated alone."""
    from magail_sumo.models.critic import TransformerCritic

    torch.manual_seed(0)
    critic = TransformerCritic(5, TINY).eval()
    sizes = [1, 7, 2, 3, 1, 40, 4, 5, 30, 3]
    group = torch.cat([torch.full((k,), g) for g, k in enumerate(sizes)] + [torch.tensor([-1])])
    perm = torch.randperm(len(group))
    group, x = group[perm], torch.randn(len(group), 5)
    with torch.no_grad():
        got = critic(x, group)
        assert got[group == -1].item() == 0.0
        for g in range(len(sizes)):
            rows = group == g
            alone = critic.forward_padded(x[rows][None], torch.ones(1, int(rows.sum()), dtype=bool))
            torch.testing.assert_close(got[rows], alone[0], atol=1e-5, rtol=1e-5)
