"""The decomposed discriminator with a transformer over each vehicle's neighbourhood
(``discriminator.kind: decomposed_transformer``): equivariance, masking, the decomposition
``D_i = e_i + Σ_j w_ij·l_ij`` read off the encoder's ego and neighbour tokens, the gradient
penalty, and a real training run that resumes exactly."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from conftest import WOMD_DIR
from magail_sumo.config import ConfigError, from_dict
from magail_sumo.models import (DecomposedConfig, DecomposedTransformerDiscriminator,
                                SetEncoderConfig)
from magail_sumo.training.discriminator_loss import DiscriminatorLossConfig, discriminator_loss

SCENE = str(WOMD_DIR / "850c48d8bbfa008f.tfrecord")


@pytest.fixture(autouse=True)
def one_torch_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _model(feature_dim=6, **kw) -> DecomposedTransformerDiscriminator:
    enc = SetEncoderConfig(embed_dim=16, num_layers=2, num_heads=2, ff_dim=32)
    model = DecomposedTransformerDiscriminator(feature_dim, DecomposedConfig(**kw), enc).eval()
    model.normalizer.update(torch.randn(500, feature_dim) * 2.0 + 0.5)
    return model


def _poses(n: int, seed: int, spread: float = 12.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 2, generator=g) * spread + torch.tensor([1650.0, -5500.0])
    yaw = (torch.rand(n, 1, generator=g) - 0.5) * 2 * math.pi
    return torch.cat([xy, yaw], 1)


def _alone(model, x):
    """e_i of raw tokens (B, V, F) as if each vehicle had no neighbour: the encoder over the
    ego token alone."""
    h = model.embed(model.normalizer(x) * model.feature_mask) + model.ego_type
    b, v, e = h.shape
    out = model.encoder(h.reshape(b * v, 1, e))
    return model.ego_head(out[:, 0]).reshape(b, v)


def test_permutation_of_vehicles_permutes_the_logits():
    torch.manual_seed(0)
    model = _model(max_neighbors=3)
    x = torch.randn(2, 6, 6)
    pos = torch.stack([_poses(6, 1), _poses(6, 2)])
    mask = torch.tensor([[1, 1, 0, 1, 1, 1], [1, 1, 1, 1, 1, 1]], dtype=torch.bool)
    tok, scene = model(x, mask, pos)
    perm = torch.tensor([4, 2, 0, 5, 3, 1])
    tok_p, scene_p = model(x[:, perm], mask[:, perm], pos[:, perm])
    torch.testing.assert_close(tok_p, tok[:, perm], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(scene_p, scene, atol=1e-5, rtol=1e-5)
    # the neighbours are in play: no vehicle's logit is its lone ego term
    assert bool((tok - _alone(model, x)).abs()[mask].min() > 1e-6)


def test_an_absent_vehicle_changes_nothing_and_gets_no_logit():
    torch.manual_seed(1)
    model = _model()
    x, pos = torch.randn(1, 4, 6), _poses(4, 3)[None]
    mask = torch.ones(1, 4, dtype=torch.bool)
    tok, scene = model(x, mask, pos)
    x5 = torch.cat([x, torch.full((1, 1, 6), 1e3)], 1)
    pos5 = torch.cat([pos, pos[:, :1] + torch.tensor([0.5, 0.0, 1.0])], 1)
    mask5 = torch.cat([mask, torch.zeros(1, 1, dtype=torch.bool)], 1)
    tok5, scene5 = model(x5, mask5, pos5)
    torch.testing.assert_close(tok5[:, :4], tok, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(scene5, scene, atol=1e-6, rtol=1e-5)
    assert tok5[0, 4] == 0
    # present, it changes vehicle 0's logit
    tok6, _ = model(x5.clamp(-3, 3), torch.ones(1, 5, dtype=torch.bool), pos5)
    assert (tok6[0, 0] - tok[0, 0]).abs() > 1e-6


def test_decomposition_is_ego_term_plus_weighted_neighbour_tokens():
    torch.manual_seed(2)
    alpha, beta, radius = 0.8, 7.0, 25.0
    model = _model(alpha=alpha, beta=beta, radius=radius, max_neighbors=4)
    x = torch.randn(1, 3, 6)
    pos = torch.tensor([[[1650.0, -5500.0, 0.3], [1659.0, -5497.0, -0.2],
                         [1640.0, -5510.0, 2.0]]])
    mask = torch.ones(1, 3, dtype=torch.bool)
    tok, scene = model(x, mask, pos)
    nb = model.neighbours(pos, mask)
    # vehicle 0's sequence by hand: ego token, then its neighbours in the order found
    xm = model.normalizer(x[0]) * model.feature_mask
    h = model.embed(xm)
    k = int(nb.valid[0, 0].sum())
    assert k == 2
    idx = nb.index[0, 0, :k]
    seq = torch.cat([(h[0] + model.ego_type)[None],
                     h[idx] + model.geometry(nb.geometry[0, 0, :k])])[None]
    out = model.encoder(seq)[0]
    e0 = model.ego_head(out[0]).squeeze()
    l0 = model.pair_head(out[1:]).squeeze(-1)
    w = alpha * torch.exp(-nb.distance[0, 0, :k] / beta)
    torch.testing.assert_close(tok[0, 0], e0 + (w * l0).sum(), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(scene[0], tok[0].mean(), atol=1e-6, rtol=1e-6)
    # alpha 0: the ego term alone (which still sees the neighbours through attention)
    model0 = _model(alpha=0.0, beta=beta, radius=radius)
    model0.load_state_dict(model.state_dict())
    tok0, _ = model0(x, mask, pos)
    torch.testing.assert_close(tok0[0, 0], e0, atol=1e-5, rtol=1e-5)


def test_a_vehicle_beyond_the_radius_is_no_neighbour():
    torch.manual_seed(3)
    model = _model(radius=20.0)
    x = torch.randn(1, 2, 6)
    far = torch.tensor([[[1650.0, -5500.0, 0.0], [1680.0, -5500.0, 0.0]]])
    tok, _ = model(x, torch.ones(1, 2, dtype=torch.bool), far)
    torch.testing.assert_close(tok, _alone(model, x), atol=1e-5, rtol=1e-5)


def test_gradient_penalty_and_loss_reach_every_part():
    torch.manual_seed(4)
    model = _model().train()
    x_e, x_p = torch.randn(4, 5, 6), torch.randn(4, 5, 6)
    mask = torch.ones(4, 5, dtype=torch.bool)
    mask[1, 3:] = False
    pos = torch.stack([_poses(5, s) for s in range(4)])
    loss = discriminator_loss(model, x_e, mask, x_p, mask, DiscriminatorLossConfig(0.1, 0.1),
                              expert_pos=pos, policy_pos=pos)
    loss.total.backward()
    assert math.isfinite(float(loss.total.detach())) and loss.gradient_penalty > 0
    for name in ("embed.weight", "ego_type", "geometry.weight", "ego_head.weight",
                 "pair_head.weight"):
        grad = dict(model.named_parameters())[name].grad
        assert grad is not None and float(grad.abs().sum()) > 0, name


def test_config_builds_the_kind_and_checks_sizes():
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.trainer import make_discriminator

    cfg = from_dict(TrainConfig, {"discriminator": {
        "kind": "decomposed_transformer", "decomposed": {"radius": 15.0, "social_coef": 0.5},
        "decomposed_transformer": {"embed_dim": 32, "num_heads": 4}}})
    assert cfg.discriminator.decomposes
    disc = make_discriminator(cfg, 226)
    assert isinstance(disc, DecomposedTransformerDiscriminator)
    assert disc.config.radius == 15.0 and disc.encoder_config.embed_dim == 32
    with pytest.raises(ConfigError, match=r"discriminator\.decomposed_transformer\.num_heads: "
                       r"must divide embed_dim"):
        from_dict(TrainConfig, {"discriminator": {"decomposed_transformer": {
            "embed_dim": 30, "num_heads": 4}}})


@pytest.mark.sumo
def test_training_with_it_resumes_exactly(tmp_path, bundled_networks):
    from magail_sumo.env.scene_specs import scene_specs
    from magail_sumo.expert import record_expert
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.trainer import load_checkpoint, train

    nets = bundled_networks("850c48d8bbfa008f")
    record_expert(scene_specs([SCENE], nets), tmp_path / "expert")
    cfg = from_dict(TrainConfig, {
        "seed": 7, "expert_dir": str(tmp_path / "expert"), "out_dir": str(tmp_path / "runs"),
        "updates": 2, "checkpoint_every": 1, "env": {"max_steps": 30},
        "scenes": {"files": [SCENE], "networks": str(nets)},
        "policy": {"actor_hidden": [16, 16], "critic_hidden": [16, 16]},
        "ppo": {"n_steps": 16, "batch_size": 16, "n_epochs": 2},
        "discriminator": {"kind": "decomposed_transformer", "epochs": 3, "batch_size": 8,
                          "decomposed": {"social_coef": 0.5},
                          "decomposed_transformer": {"embed_dim": 16, "num_heads": 2,
                                                     "ff_dim": 32}}})
    straight = train(cfg, run_dir=tmp_path / "straight", log=lambda s: None)
    half = train(replace(cfg, updates=1), run_dir=tmp_path / "split", log=lambda s: None)
    resumed = train(cfg, resume=half, log=lambda s: None)
    a = load_checkpoint(straight / "checkpoints" / "latest.pt")
    b = load_checkpoint(resumed / "checkpoints" / "latest.pt")
    assert a["update"] == b["update"] == 2
    assert any(k.startswith("encoder.") for k in a["discriminator"])
    for key in ("policy", "discriminator"):
        for k in a[key]:
            assert torch.equal(a[key][k], b[key][k]), (key, k)
    first = load_checkpoint(straight / "checkpoints" / "update_000001.pt")["discriminator"]
    assert not torch.equal(first["pair_head.weight"], a["discriminator"]["pair_head.weight"])
