"""Discriminators: masking, permutation equivariance, per-token context, loss and learning."""

from __future__ import annotations

import torch

from magail_sumo.models import (
    MLPDiscriminator, RunningNormalizer, TransformerConfig, TransformerDiscriminator, imitation_reward,
)
from magail_sumo.training.discriminator_loss import discriminator_loss

SMALL = TransformerConfig(embed_dim=32, num_layers=2, num_heads=4, ff_dim=64, dropout=0.0)


def test_normalizer_matches_batch_statistics_and_clips():
    torch.manual_seed(0)
    data = torch.randn(1000, 3, dtype=torch.float64) * torch.tensor([1.0, 5.0, 0.1]) + 3.0
    norm = RunningNormalizer(3, clip=10.0)
    for chunk in data.split(137):
        norm.update(chunk)
    torch.testing.assert_close(norm.mean, data.mean(0))
    torch.testing.assert_close(norm.std, data.std(0, unbiased=False), rtol=1e-6, atol=1e-6)
    assert float(norm(torch.full((1, 3), 1e6, dtype=torch.float64)).max()) == 10.0
    restored = RunningNormalizer(3)
    restored.load_state_dict(norm.state_dict())
    torch.testing.assert_close(restored.mean, norm.mean)


def test_padding_is_ignored_and_order_does_not_matter():
    torch.manual_seed(0)
    model = TransformerDiscriminator(6, SMALL).eval()
    x = torch.randn(2, 5, 6)
    mask = torch.tensor([[1, 1, 1, 0, 0], [1, 1, 1, 1, 1]], dtype=torch.bool)
    tok, scene = model(x, mask)
    garbage = x.clone()
    garbage[0, 3:] = 1e3  # padded tokens may hold anything
    tok2, scene2 = model(garbage, mask)
    torch.testing.assert_close(tok[0], tok2[0])
    torch.testing.assert_close(scene[0], scene2[0])
    perm = torch.tensor([4, 2, 0, 3, 1])
    tok3, scene3 = model(x[1:, perm], mask[1:, perm])
    torch.testing.assert_close(tok3[0], tok[1, perm], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(scene3, scene[1:], atol=1e-5, rtol=1e-5)
    assert torch.all(tok[0, 3:] == 0)


def test_token_logits_depend_on_the_other_vehicles_only_for_the_transformer():
    torch.manual_seed(1)
    x = torch.randn(1, 4, 6)
    mask = torch.ones(1, 4, dtype=torch.bool)
    other = x.clone()
    other[0, 3] += 2.0
    for model, changes in ((TransformerDiscriminator(6, SMALL).eval(), True),
                           (MLPDiscriminator(6).eval(), False)):
        a, _ = model(x, mask)
        b, _ = model(other, mask)
        assert bool(torch.any((a[0, :3] - b[0, :3]).abs() > 1e-6)) is changes


def test_loss_gradient_penalty_and_learning_to_separate():
    torch.manual_seed(0)
    model = TransformerDiscriminator(4, SMALL)
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3, weight_decay=1e-4)
    expert = torch.randn(64, 6, 4) + torch.tensor([1.0, 0.0, 0.0, 0.0])
    policy = torch.randn(64, 6, 4) - torch.tensor([1.0, 0.0, 0.0, 0.0])
    mask = torch.rand(64, 6) > 0.2
    model.normalizer.update(torch.cat([expert[mask], policy[mask]]))
    first = discriminator_loss(model, expert, mask, policy, mask)
    assert first.gradient_penalty > 0 and first.logit_penalty > 0
    for _ in range(60):
        loss = discriminator_loss(model, expert, mask, policy, mask)
        opt.zero_grad()
        loss.total.backward()
        opt.step()
    assert loss.bce < first.bce * 0.6
    assert loss.expert_accuracy > 0.8 and loss.policy_accuracy > 0.8
    tok, _ = model(expert, mask)
    r = imitation_reward(tok)
    assert torch.all(r >= 0) and torch.all(r <= -torch.log(torch.tensor(1e-4)) + 1e-6)


def test_ignored_features_reach_neither_logits_nor_gradient_penalty():
    torch.manual_seed(0)
    for disc in (TransformerDiscriminator(6, TransformerConfig(16, 1, 2, 32, 0.0)),
                 MLPDiscriminator(6, (16,))):
        disc.eval()
        disc.normalizer.update(torch.randn(200, 6) * 3.0 + 1.0)
        disc.ignore_features([1, 4])
        x, mask = torch.randn(2, 3, 6), torch.ones(2, 3, dtype=torch.bool)
        y = x.clone()
        y[..., [1, 4]] = torch.randn(2, 3, 2) * 50.0
        assert torch.equal(disc(x, mask)[0], disc(y, mask)[0])
        z = x.clone()
        z[..., 0] += 1.0
        assert not torch.allclose(disc(x, mask)[0], disc(z, mask)[0])
        xe = disc.normalizer(x).requires_grad_(True)
        grad, = torch.autograd.grad(disc.forward_normalized(xe, mask)[0].sum(), xe)
        assert torch.all(grad[..., [1, 4]] == 0) and torch.any(grad[..., 0] != 0)
        # a state dict from before the mask existed loads as "judge every feature"
        state = {k: v for k, v in disc.state_dict().items() if k != "feature_mask"}
        disc.load_state_dict(state)
        assert torch.all(disc.feature_mask == 1)


def test_make_discriminator_masks_named_features_in_s_and_s_next():
    import pytest

    from magail_sumo.config import ConfigError, from_dict
    from magail_sumo.sensors.observation import observation_names
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.trainer import make_discriminator

    names = observation_names()
    cfg = from_dict(TrainConfig, {"discriminator": {"ignore_features": ["prev_accel",
                                                                         "prev_steer"]}})
    disc = make_discriminator(cfg, 2 * len(names))
    off = torch.nonzero(disc.feature_mask == 0).flatten().tolist()
    a, s = names.index("prev_accel"), names.index("prev_steer")
    assert off == sorted([a, s, len(names) + a, len(names) + s])
    with pytest.raises(ConfigError, match="ignore_features: unknown observation feature"):
        from_dict(TrainConfig, {"discriminator": {"ignore_features": ["prev_brake"]}})
