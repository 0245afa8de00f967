"""Decomposed discriminators (ego–map + distance-weighted ego–neighbour terms), with MLP heads
(``kind: decomposed``) and with a transformer over each vehicle's neighbourhood
(``kind: decomposed_transformer``): equivariance, masking, distance weights, neighbourhood
limits, the decomposition read off the encoder's tokens, gradient penalty, social reward, expert
poses (format /1 vs /2), env poses, and real training runs of both kinds with exact resume."""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch

from conftest import WOMD_DIR
from magail_sumo.config import ConfigError, from_dict
from magail_sumo.models import (DecomposedConfig, DecomposedDiscriminator,
                                DecomposedTransformerDiscriminator, SetEncoderConfig)
from magail_sumo.training.discriminator_loss import DiscriminatorLossConfig, discriminator_loss

SCENE = str(WOMD_DIR / "850c48d8bbfa008f.tfrecord")


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Tiny models: a second spinning thread on a busy machine only slows them down."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


#: the transformer kind's encoder in these tests
TINY_ENCODER = SetEncoderConfig(embed_dim=16, num_layers=2, num_heads=2, ff_dim=32)
#: assert_close tolerances per kind where the transformer's float error needs its own
TOL = {"mlp": {}, "transformer": {"atol": 1e-6, "rtol": 1e-5}}


def _model(feature_dim=6, kind="mlp", **kw):
    """A small decomposed discriminator of ``kind`` ("mlp" heads or "transformer")."""
    cfg = DecomposedConfig(**{"ego_hidden": (16,), "pair_hidden": (16, 8), **kw})
    model = DecomposedDiscriminator(feature_dim, cfg) if kind == "mlp" else \
        DecomposedTransformerDiscriminator(feature_dim, cfg, TINY_ENCODER)
    model.eval().normalizer.update(torch.randn(500, feature_dim) * 2.0 + 0.5)
    return model


def _poses(n: int, seed: int, spread: float = 12.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 2, generator=g) * spread + torch.tensor([1650.0, -5500.0])
    yaw = (torch.rand(n, 1, generator=g) - 0.5) * 2 * math.pi
    return torch.cat([xy, yaw], 1)


def _ego(model, x):
    """e_i of raw tokens (B, V, F), computed from the module's ego MLP."""
    return model.ego(model.normalizer(x) * model.feature_mask).squeeze(-1)


def _alone(model, x):
    """e_i of raw tokens (B, V, F) as if each vehicle had no neighbour: the ego MLP, or the
    transformer kind's encoder over the ego token alone."""
    if isinstance(model, DecomposedDiscriminator):
        return _ego(model, x)
    h = model.embed(model.normalizer(x) * model.feature_mask) + model.ego_type
    b, v, e = h.shape
    out = model.encoder(h.reshape(b * v, 1, e))
    return model.ego_head(out[:, 0]).reshape(b, v)


@pytest.mark.parametrize("kind", ["mlp", "transformer"])
def test_permutation_of_vehicles_permutes_the_logits(kind):
    torch.manual_seed(0)
    model = _model(kind=kind, max_neighbors=3)
    x = torch.randn(2, 6, 6)
    pos = torch.stack([_poses(6, 1), _poses(6, 2)])
    mask = torch.tensor([[1, 1, 0, 1, 1, 1], [1, 1, 1, 1, 1, 1]], dtype=torch.bool)
    tok, scene = model(x, mask, pos)
    perm = torch.tensor([4, 2, 0, 5, 3, 1])
    tok_p, scene_p = model(x[:, perm], mask[:, perm], pos[:, perm])
    torch.testing.assert_close(tok_p, tok[:, perm], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(scene_p, scene, atol=1e-5, rtol=1e-5)
    # every vehicle has neighbours here: the pairwise terms are in play
    assert bool((tok - _alone(model, x)).abs()[mask].min() > 1e-6)


@pytest.mark.parametrize("kind", ["mlp", "transformer"])
def test_an_absent_vehicle_changes_nothing(kind):
    torch.manual_seed(1)
    model = _model(kind=kind)
    x, pos = torch.randn(1, 4, 6), _poses(4, 3)[None]
    mask = torch.ones(1, 4, dtype=torch.bool)
    tok, scene = model(x, mask, pos)
    # a fifth, absent slot holding garbage right next to vehicle 0
    x5 = torch.cat([x, torch.full((1, 1, 6), 1e3)], 1)
    pos5 = torch.cat([pos, pos[:, :1] + torch.tensor([0.5, 0.0, 1.0])], 1)
    mask5 = torch.cat([mask, torch.zeros(1, 1, dtype=torch.bool)], 1)
    tok5, scene5 = model(x5, mask5, pos5)
    torch.testing.assert_close(tok5[:, :4], tok, **TOL[kind])
    torch.testing.assert_close(scene5, scene, **TOL[kind])
    assert tok5[0, 4] == 0
    # the same vehicle present does change vehicle 0's logit
    tok6, _ = model(x5.clamp(-3, 3), torch.ones(1, 5, dtype=torch.bool), pos5)
    assert (tok6[0, 0] - tok[0, 0]).abs() > 1e-6
    # an absent vehicle gets no logit and gives its neighbours none of its terms
    masked = mask.clone()
    masked[0, 2] = False
    tok_m, _ = model(x, masked, pos)
    three, _ = model(x[:, [0, 1, 3]], mask[:, [0, 1, 3]], pos[:, [0, 1, 3]])
    torch.testing.assert_close(tok_m[:, [0, 1, 3]], three, **TOL[kind])
    assert tok_m[0, 2] == 0


def test_a_single_vehicle_gets_only_its_ego_term():
    torch.manual_seed(2)
    model = _model()
    x, pos = torch.randn(3, 1, 6), _poses(3, 4)[:, None]
    tok, scene = model(x, torch.ones(3, 1, dtype=torch.bool), pos)
    torch.testing.assert_close(tok, _ego(model, x))
    torch.testing.assert_close(scene, tok[:, 0])


def _two(d: float, yaw0: float = 0.3, yaw1: float = -0.4, bearing: float = 0.7):
    """Vehicle 0 at a scene point, vehicle 1 at distance d in scene direction ``bearing``."""
    p0 = torch.tensor([1650.0, -5500.0, yaw0])
    p1 = p0 + torch.tensor([d * math.cos(bearing), d * math.sin(bearing), yaw1 - yaw0])
    return torch.stack([p0, p1])[None]


def test_pairwise_term_has_weight_alpha_exp_minus_d_over_beta():
    torch.manual_seed(3)
    alpha, beta, radius = 0.7, 6.0, 25.0
    model = _model(alpha=alpha, beta=beta, radius=radius)
    x = torch.randn(1, 2, 6)
    mask = torch.ones(1, 2, dtype=torch.bool)
    d = 9.0
    pos = _two(d)
    tok, _ = model(x, mask, pos)
    # the pairwise logit l_01 by hand: geometry of vehicle 1 in vehicle 0's frame
    xm = model.normalizer(x) * model.feature_mask
    rel = math.atan2(math.sin(0.7 - 0.3), math.cos(0.7 - 0.3))
    geo = torch.tensor([d * math.cos(rel) / radius, d * math.sin(rel) / radius,
                        math.cos(-0.7), math.sin(-0.7), d / radius])
    pre = model.pair_i(xm[0, 0]) + model.pair_j(xm[0, 1]) + model.pair_geometry(geo)
    l01 = model.pair_rest(pre).squeeze()
    w = alpha * math.exp(-d / beta)
    torch.testing.assert_close(tok[0, 0], _ego(model, x)[0, 0] + w * l01, atol=1e-5, rtol=1e-5)
    nb = model.neighbours(pos, mask)
    dist = nb.distance[0, 0, 0].item()  # d up to the float32 rounding of the poses (~0.1 mm)
    assert dist == pytest.approx(d, abs=1e-3)
    assert nb.weight[0, 0, 0].item() == pytest.approx(alpha * math.exp(-dist / beta), rel=1e-6)
    assert nb.weight[0, 1, 0].item() == pytest.approx(alpha * math.exp(-dist / beta), rel=1e-6)


def test_a_farther_neighbour_contributes_less_and_none_beyond_the_radius():
    torch.manual_seed(4)
    alpha, beta, radius = 1.0, 10.0, 30.0
    model = _model(alpha=alpha, beta=beta, radius=radius)
    with torch.no_grad():  # pair logit independent of the geometry: only the weight varies
        model.pair_geometry.weight.zero_()
    x = torch.randn(1, 2, 6)
    mask = torch.ones(1, 2, dtype=torch.bool)
    ego = _ego(model, x)[0, 0]
    contrib = {d: float(model(x, mask, _two(d))[0][0, 0].detach() - ego.detach())
               for d in (5.0, 15.0, 29.9)}
    assert abs(contrib[5.0]) > abs(contrib[15.0]) > abs(contrib[29.9]) > 0
    assert contrib[15.0] / contrib[5.0] == pytest.approx(math.exp(-10.0 / beta), rel=1e-4)
    for d in (30.5, 200.0):  # beyond the radius: ego term only
        torch.testing.assert_close(model(x, mask, _two(d))[0][0, 0], ego)


def test_only_the_k_nearest_neighbours_count():
    torch.manual_seed(5)
    model = _model(max_neighbors=2)
    x = torch.randn(1, 4, 6)
    mask = torch.ones(1, 4, dtype=torch.bool)
    base = torch.tensor([1650.0, -5500.0, 0.0])
    pos = torch.stack([base, base + torch.tensor([4.0, 0, 0]), base + torch.tensor([0, 8.0, 0]),
                       base + torch.tensor([-15.0, 0, 0])])[None]
    tok, _ = model(x, mask, pos)
    far = x.clone()
    far[0, 3] += 3.0  # vehicle 3 is vehicle 0's third nearest
    near = x.clone()
    near[0, 2] += 3.0  # vehicle 2 its second nearest
    assert model(far, mask, pos)[0][0, 0] == tok[0, 0]
    assert (model(near, mask, pos)[0][0, 0] - tok[0, 0]).abs() > 1e-6
    nb = model.neighbours(pos, mask)
    assert nb.index[0, 0].tolist() == [1, 2] and bool(nb.valid.all())


def test_normalised_weights_sum_to_alpha():
    model = _model(alpha=0.8, beta=5.0, normalize_weights=True, max_neighbors=3)
    pos = torch.stack([_poses(5, 6), _poses(5, 7, spread=80.0)])
    mask = torch.tensor([[1, 1, 1, 1, 1], [1, 1, 1, 1, 0]], dtype=torch.bool)
    nb = model.neighbours(pos, mask)
    sums = nb.weight.sum(-1)
    has = nb.valid.any(-1)
    torch.testing.assert_close(sums[has], torch.full_like(sums[has], 0.8))
    assert torch.all(sums[~has] == 0) and bool(torch.isfinite(nb.weight).all())
    d = nb.distance[0, 0]
    e = torch.exp(-d / 5.0)
    torch.testing.assert_close(nb.weight[0, 0], 0.8 * e / e.sum())


def _dense_weights(pos: np.ndarray, mask: np.ndarray, alpha, beta, radius, k) -> np.ndarray:
    """W[b, i, j] by explicit loops (the test's own reading of the definition)."""
    b_, v = mask.shape
    w = np.zeros((b_, v, v))
    for b in range(b_):
        for i in range(v):
            if not mask[b, i]:
                continue
            cand = []
            for j in range(v):
                if j != i and mask[b, j]:
                    d = math.hypot(*(pos[b, j, :2] - pos[b, i, :2]))
                    if d <= radius:
                        cand.append((d, j))
            for d, j in sorted(cand)[:k]:
                w[b, i, j] = alpha * math.exp(-d / beta)
    return w


def test_gradient_penalty_equals_the_hand_computation():
    """Linear heads: ∂(Σ_i D_i)/∂x̂_k = a + (Σ_j w_kj)·u + (Σ_i w_ik)·v, so the penalty is the
    mean over present vehicles of its squared norm."""
    torch.manual_seed(6)
    alpha, beta, radius, k = 0.9, 7.0, 20.0, 2
    model = DecomposedDiscriminator(4, DecomposedConfig(
        ego_hidden=(), pair_hidden=(), alpha=alpha, beta=beta, radius=radius, max_neighbors=k))
    model.normalizer.update(torch.randn(300, 4))
    x = torch.randn(2, 4, 4)
    pos = torch.stack([_poses(4, 8, spread=25.0), _poses(4, 9, spread=25.0)])
    mask = torch.tensor([[1, 1, 1, 0], [1, 1, 1, 1]], dtype=torch.bool)
    out = discriminator_loss(model, x, mask, torch.randn(2, 4, 4), mask,
                             expert_pos=pos, policy_pos=pos)
    a = model.ego[0].weight[0].detach().double().numpy()
    u = model.pair_i.weight[0].detach().double().numpy()
    v = model.pair_j.weight[0].detach().double().numpy()
    w = _dense_weights(pos.double().numpy(), mask.numpy(), alpha, beta, radius, k)
    m = mask.numpy()
    grad = a + w.sum(2)[..., None] * u + w.sum(1)[..., None] * v  # (B, V, F)
    want = float((grad ** 2).sum(-1)[m].mean())
    assert math.isfinite(out.gradient_penalty) and out.gradient_penalty > 0
    assert out.gradient_penalty == pytest.approx(want, rel=1e-4)
    assert w[0, 3].sum() == 0 and w[0, :, 3].sum() == 0  # the absent vehicle: no pair terms


def test_loss_needs_poses_and_the_pair_head_learns_what_the_ego_head_cannot():
    """Expert pairs share the sign of feature 0, policy pairs have opposite signs: each
    vehicle alone looks the same on both sides, only the pairwise head can tell them apart."""
    torch.manual_seed(7)
    n = 128
    sign = torch.randint(0, 2, (n, 1)).float() * 2 - 1
    expert = torch.cat([sign, sign], 1)[..., None] + 0.1 * torch.randn(n, 2, 1)
    policy = torch.cat([sign, -sign], 1)[..., None] + 0.1 * torch.randn(n, 2, 1)
    pos = _two(6.0).expand(n, 2, 3)
    mask = torch.ones(n, 2, dtype=torch.bool)
    accuracy = {}
    for alpha in (0.0, 1.0):
        model = DecomposedDiscriminator(1, DecomposedConfig(
            ego_hidden=(16,), pair_hidden=(16,), alpha=alpha))
        model.normalizer.update(torch.cat([expert, policy]).reshape(-1, 1))
        with pytest.raises(ValueError, match="needs the vehicles' poses"):
            discriminator_loss(model, expert, mask, policy, mask)
        opt = torch.optim.Adam(model.parameters(), lr=1e-2)
        for _ in range(150):
            out = discriminator_loss(model, expert, mask, policy, mask, expert_pos=pos,
                                     policy_pos=pos)
            opt.zero_grad()
            out.total.backward()
            opt.step()
        accuracy[alpha] = 0.5 * (out.expert_accuracy + out.policy_accuracy)
    assert accuracy[1.0] > 0.95 and accuracy[0.0] < 0.7


def test_social_reward_arithmetic():
    torch.manual_seed(8)
    alpha, beta, radius, k, lam = 1.3, 8.0, 15.0, 2, 0.4
    model = _model(alpha=alpha, beta=beta, radius=radius, max_neighbors=k)
    pos = torch.stack([_poses(5, 10, spread=20.0), _poses(5, 11, spread=20.0)])
    mask = torch.tensor([[1, 1, 1, 1, 1], [1, 0, 1, 1, 1]], dtype=torch.bool)
    r = torch.rand(2, 5).masked_fill(~mask, 0.0)
    got = model.social_reward(r, pos, mask, lam)
    w = _dense_weights(pos.double().numpy(), mask.numpy(), alpha, beta, radius, k)
    want = r.double().numpy() + lam * np.einsum("bij,bj->bi", w, r.double().numpy())
    np.testing.assert_allclose(got.numpy(), want * mask.numpy(), rtol=1e-5, atol=1e-6)
    assert w.sum() > 0 and not np.allclose(got.numpy(), r.numpy())
    assert torch.equal(model.social_reward(r, pos, mask, 0.0), r)


# ------------------------------------------------ the transformer kind (decomposed_transformer)
def test_transformer_kind_is_ego_term_plus_weighted_neighbour_tokens():
    torch.manual_seed(2)
    alpha, beta, radius = 0.8, 7.0, 25.0
    model = _model(kind="transformer", alpha=alpha, beta=beta, radius=radius,
                   max_neighbors=4)
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
    model0 = _model(kind="transformer", alpha=0.0, beta=beta, radius=radius)
    model0.load_state_dict(model.state_dict())
    tok0, _ = model0(x, mask, pos)
    torch.testing.assert_close(tok0[0, 0], e0, atol=1e-5, rtol=1e-5)


def test_transformer_kind_sees_no_vehicle_beyond_the_radius():
    torch.manual_seed(3)
    model = _model(kind="transformer", radius=20.0)
    x = torch.randn(1, 2, 6)
    far = torch.tensor([[[1650.0, -5500.0, 0.0], [1680.0, -5500.0, 0.0]]])
    tok, _ = model(x, torch.ones(1, 2, dtype=torch.bool), far)
    torch.testing.assert_close(tok, _alone(model, x), atol=1e-5, rtol=1e-5)


def test_transformer_kind_gradient_penalty_and_loss_reach_every_part():
    torch.manual_seed(4)
    model = _model(kind="transformer").train()
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


def test_config_builds_the_transformer_kind_and_checks_sizes():
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


def test_config_range_checks_and_kind():
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.trainer import make_discriminator

    for key, value, msg in (("beta", 0.0, "must be > 0"), ("radius", -1.0, "must be > 0"),
                            ("alpha", -0.5, "must be >= 0"), ("max_neighbors", 0, "must be >= 1"),
                            ("social_coef", -1.0, "must be >= 0"),
                            ("pair_hidden", [0], "layer sizes must be >= 1")):
        with pytest.raises(ConfigError, match=rf"discriminator\.decomposed\.{key}: {msg}"):
            from_dict(TrainConfig, {"discriminator": {"decomposed": {key: value}}})
    with pytest.raises(ConfigError, match="must be one of transformer, mlp, decomposed, "
                       "decomposed_transformer"):
        from_dict(TrainConfig, {"discriminator": {"kind": "decomp"}})
    cfg = from_dict(TrainConfig, {"discriminator": {
        "kind": "decomposed", "ignore_features": ["prev_accel"],
        "decomposed": {"ego_hidden": [8], "pair_hidden": [4], "radius": 12.5}}})
    disc = make_discriminator(cfg, 226)
    assert isinstance(disc, DecomposedDiscriminator) and disc.config.radius == 12.5
    assert int((disc.feature_mask == 0).sum()) == 2


# ------------------------------------------------------------------ real scenes (SUMO)
@pytest.fixture(scope="module")
def setup(tmp_path_factory, bundled_networks):
    from magail_sumo.env.scene_specs import scene_specs
    from magail_sumo.expert import record_expert
    from magail_sumo.training.config import TrainConfig

    root = tmp_path_factory.mktemp("decomposed")
    nets = bundled_networks("850c48d8bbfa008f")
    record_expert(scene_specs([SCENE], nets), root / "expert")
    cfg = from_dict(TrainConfig, {
        "seed": 5, "expert_dir": str(root / "expert"), "out_dir": str(root / "runs"),
        "updates": 2, "checkpoint_every": 1,
        "env": {"max_steps": 30},
        "scenes": {"files": [SCENE], "networks": str(nets)},
        "policy": {"actor_hidden": [16, 16], "critic_hidden": [16, 16]},
        "ppo": {"n_steps": 16, "batch_size": 16, "n_epochs": 2},
        "discriminator": {"kind": "decomposed", "epochs": 3, "batch_size": 8, "decomposed": {
            "ego_hidden": [16], "pair_hidden": [16], "social_coef": 0.5}}})
    return root, cfg


def _as_format_1(src, dst):
    """A copy of an expert dir as the /1 format wrote it: no pose columns."""
    import pyarrow.parquet as pq

    shutil.copytree(src, dst)
    meta = json.loads((dst / "metadata.json").read_text())
    meta["format"] = "magail_sumo.expert/1"
    (dst / "metadata.json").write_text(json.dumps(meta))
    for sc in meta["scenes"]:
        t = pq.read_table(dst / sc["parquet"])
        pq.write_table(t.drop_columns(["x", "y", "yaw"]), dst / sc["parquet"])
    return dst


@pytest.mark.sumo
def test_expert_poses_format_2_and_format_1(setup, tmp_path):
    from converters import load_scene
    from magail_sumo.expert import EXPERT_FORMAT, ExpertDataError, ExpertDataset
    from magail_sumo.training.trainer import GailRun, train

    root, cfg = setup
    ds = ExpertDataset(root / "expert")
    assert EXPERT_FORMAT == "magail_sumo.expert/2" and ds.format == EXPERT_FORMAT
    assert ds.pos.shape == (len(ds), 3) and ds.pos.dtype == np.float32
    # the pose at a track's first step is its logged pose (the env starts it there)
    tr = load_scene(SCENE).tracks
    row_of = {int(t): k for k, t in enumerate(tr.id.tolist())}
    for track in np.unique(ds.track):
        i = np.flatnonzero(ds.track == track)[0]  # rows are sorted by step
        r, t = row_of[int(track)], int(ds.step[i])
        np.testing.assert_allclose(ds.pos[i, :2], [tr.x[r, t], tr.y[r, t]], atol=1e-3)
        assert math.cos(ds.pos[i, 2] - tr.heading[r, t]) > 0.9999
    batch = ds.sample_scene_steps(16, np.random.default_rng(0))
    assert batch.pos.shape == batch.x.shape[:2] + (3,)
    assert np.all(batch.pos[~batch.mask] == 0) and np.all(batch.pos[batch.mask][:, :2] != 0)
    # the same steps with a /1 copy: same tokens, no poses, refused for the decomposed kind
    old = ExpertDataset(_as_format_1(root / "expert", tmp_path / "old"))
    assert old.pos is None and np.array_equal(old.tokens, ds.tokens)
    assert old.sample_scene_steps(4, np.random.default_rng(0)).pos is None
    with pytest.raises(ExpertDataError, match=r"format magail_sumo.expert/1 has no vehicle "
                       r"poses.*re-record it with `magail-sumo expert") as err:
        GailRun(cfg, old)
    assert "\n" not in str(err.value)
    with pytest.raises(ExpertDataError, match="re-record"):
        train(replace(cfg, expert_dir=str(tmp_path / "old")), run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()
    # the other kinds train on /1 data as before
    mlp = replace(cfg, expert_dir=str(tmp_path / "old"), updates=1, discriminator=replace(
        cfg.discriminator, kind="mlp", mlp_hidden=(8,)))
    train(mlp, run_dir=tmp_path / "mlp", log=lambda s: None)
    # a /2 file without the pose columns is named
    broken = _as_format_1(root / "expert", tmp_path / "broken")
    meta = json.loads((broken / "metadata.json").read_text())
    meta["format"] = EXPERT_FORMAT
    (broken / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(ExpertDataError, match="lacks the column.*x, y, yaw"):
        ExpertDataset(broken)


@pytest.mark.sumo
def test_vec_env_reports_each_slots_pose(setup):
    from magail_sumo.env import EnvConfig
    from magail_sumo.env.vec_env import MultiSceneVecEnv
    from magail_sumo.env.scene_specs import scene_specs

    root, cfg = setup
    venv = MultiSceneVecEnv(scene_specs([SCENE], cfg.scenes.networks), EnvConfig(max_steps=20),
                            seed=2)
    rng = np.random.default_rng(0)

    def agent_poses():
        st = venv.env_method("agent_states", indices=[0])[0]
        return np.stack([st.state.x, st.state.y, st.state.yaw], 1).astype(np.float32)

    def rows(a):
        return a[np.lexsort(a.T[::-1])]

    try:
        venv.reset()
        for _ in range(12):
            act = venv.slot_active
            assert np.all(venv.slot_pos[~act] == 0)
            np.testing.assert_array_equal(rows(venv.slot_pos[act]), rows(agent_poses()))
            before = venv.slot_pos.copy()
            venv.step(rng.uniform(-1, 1, (venv.num_envs, 2)))
            assert np.array_equal(venv.prev_slot_pos, before)
        state, pos = venv.get_state(), venv.slot_pos.copy()
        venv.set_state(state)
        assert np.array_equal(venv.slot_pos, pos)
    finally:
        venv.close()


@pytest.mark.sumo
def test_deferred_rewards_with_poses_equal_per_step_rewards(setup):
    """The deferred (batched, trimmed) rewards of the decomposed discriminator with the social
    reward equal the per-step ones: the poses travel with their scene steps."""
    from magail_sumo.expert import ExpertDataset
    from magail_sumo.sensors.observation import observation_names
    from magail_sumo.training.trainer import GailRun

    root, cfg = setup
    expert = ExpertDataset(cfg.expert_dir, observation_names(cfg.env.observation))
    got = []
    for deferred in (True, False):
        torch.manual_seed(0)
        np.random.seed(0)
        run = GailRun(cfg, expert)
        try:
            assert run.wrapper.social_coef == 0.5
            run.policy.obs_normalizer.update(torch.as_tensor(expert.s))
            if not deferred:
                run.wrapper.deferred = False
                run.model.rollout_buffer.reward_source = None
            fit, seen = run.disc_trainer.train, []  # keep what the discriminator trains on
            run.disc_trainer.train = lambda data: (seen.append(data), fit(data))[1]
            run.run_update()
            buf = run.model.rollout_buffer
            got.append((buf.rewards.copy(), buf.active.copy()))
            data, = seen
            assert data.pos.shape == data.x.shape[:2] + (3,)
            assert np.all(data.pos[~data.mask] == 0) and np.all(data.pos[data.mask][:, :2] != 0)
        finally:
            run.close()
    (r_def, a_def), (r_step, a_step) = got
    assert np.array_equal(a_def, a_step) and a_def.any()
    assert np.allclose(r_def, r_step, atol=1e-5) and np.abs(r_def[a_def]).max() > 0


@pytest.mark.sumo
@pytest.mark.parametrize("kind,prefix,moved", [
    ("decomposed", "pair_", "pair_j.weight"),
    ("decomposed_transformer", "encoder.", "pair_head.weight")])
def test_decomposed_training_resumes_exactly(setup, kind, prefix, moved):
    from magail_sumo.training.trainer import load_checkpoint, train

    root, cfg = setup
    cfg = replace(cfg, discriminator=replace(cfg.discriminator, kind=kind,
                                             decomposed_transformer=TINY_ENCODER))
    straight = train(cfg, run_dir=root / f"straight-{kind}", log=lambda s: None)
    half = train(replace(cfg, updates=1), run_dir=root / f"split-{kind}", log=lambda s: None)
    resumed = train(cfg, resume=half, log=lambda s: None)
    a = load_checkpoint(straight / "checkpoints" / "latest.pt")
    b = load_checkpoint(resumed / "checkpoints" / "latest.pt")
    assert a["update"] == b["update"] == 2
    assert any(k.startswith(prefix) for k in a["discriminator"])
    for key in ("policy", "discriminator"):
        assert a[key].keys() == b[key].keys()
        for k in a[key]:
            assert torch.equal(a[key][k], b[key][k]), (key, k)
    assert a["num_timesteps"] == b["num_timesteps"]
    # the discriminator did train (its weights moved from the first checkpoint)
    first = load_checkpoint(straight / "checkpoints" / "update_000001.pt")["discriminator"]
    assert not torch.equal(first[moved], a["discriminator"][moved])


def test_every_configurable_kind_has_a_builder_and_no_other():
    """``discriminator.kind``'s choices (the config layer, no torch) and the builders'
    registry (the training layer) name the same kinds."""
    from magail_sumo.training.adversarial import DISCRIMINATORS
    from magail_sumo.training.config import DISCRIMINATOR_KINDS

    assert sorted(DISCRIMINATORS) == sorted(DISCRIMINATOR_KINDS)
