"""PPO update with the behavioural-cloning regulariser (``ppo.bc_coef``): our MaskedPPO.train is
SB3's PPO update bit for bit without it; with it the expert NLL falls, its weight decays per
update, and a run with it resumes exactly."""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pytest
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.utils import FloatSchedule

from conftest import WOMD_DIR
from magail_sumo.config import ConfigError, MAX_MESSAGE, from_dict, load_config
from magail_sumo.env.scene_specs import scene_specs
from magail_sumo.expert import ExpertDataset, record_expert
from magail_sumo.sensors.observation import observation_names
from magail_sumo.training.bc import expert_actions, expert_nll
from magail_sumo.training.config import TrainConfig
from magail_sumo.training.gail.config import PPOConfig
from magail_sumo.training.trainer import GailRun, load_checkpoint, train

SCENE = str(WOMD_DIR / "850c48d8bbfa008f.tfrecord")


@pytest.fixture(scope="module")
def setup(tmp_path_factory, bundled_networks):
    root = tmp_path_factory.mktemp("bcreg")
    nets = bundled_networks("850c48d8bbfa008f")
    record_expert(scene_specs([SCENE], nets), root / "expert")
    cfg = from_dict(TrainConfig, {
        "seed": 5, "expert_dir": str(root / "expert"), "out_dir": str(root / "runs"),
        "updates": 2, "checkpoint_every": 1, "env": {"max_steps": 30},
        "scenes": {"files": [SCENE], "networks": str(nets)},
        "policy": {"actor_hidden": [16, 16], "critic_hidden": [16, 16]},
        "ppo": {"n_steps": 16, "batch_size": 16, "n_epochs": 2, "bc_coef": 0.5,
                "bc_decay": 0.8, "bc_batch_size": 32},
        "discriminator": {"epochs": 2, "batch_size": 8, "transformer": {
            "embed_dim": 16, "num_layers": 1, "num_heads": 2, "ff_dim": 32}}})
    expert = ExpertDataset(cfg.expert_dir, observation_names(cfg.env.observation))
    return root, cfg, expert


@pytest.fixture(scope="module")
def filled(setup):
    """A GailRun (bc_coef 0.5) after one real update: a filled rollout buffer, and its state."""
    _, cfg, expert = setup
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    run = GailRun(cfg, expert)
    run.policy.obs_normalizer.update(torch.as_tensor(expert.s))
    run.run_update()
    yield run, _snapshot(run.model)
    run.close()


def _snapshot(m) -> dict:
    return {"policy": copy.deepcopy(m.policy.state_dict()),
            "optim": copy.deepcopy(m.policy.optimizer.state_dict()),
            "n_updates": m._n_updates, "bc_updates": m.bc_updates, "lr": m.learning_rate,
            "bc_rng": copy.deepcopy(m.bc_rng.bit_generator.state),
            "np": np.random.get_state(), "torch": torch.get_rng_state()}


def _restore(m, snap: dict, **settings) -> None:
    m.policy.load_state_dict(snap["policy"])
    m.policy.optimizer.load_state_dict(copy.deepcopy(snap["optim"]))
    m._n_updates, m.bc_updates = snap["n_updates"], snap["bc_updates"]
    m.set_learning_rate(snap["lr"])
    m.bc_rng.bit_generator.state = snap["bc_rng"]
    np.random.set_state(snap["np"])
    torch.set_rng_state(snap["torch"])
    for k, v in settings.items():
        setattr(m, k, v)


def _params(m) -> dict[str, torch.Tensor]:
    out = {f"policy.{k}": v.clone() for k, v in m.policy.state_dict().items()}
    for i, st in m.policy.optimizer.state_dict()["state"].items():
        out.update({f"adam.{i}.{n}": torch.as_tensor(v).clone() for n, v in st.items()})
    return out


def _nll(m, expert) -> float:
    with torch.no_grad():
        return float(expert_nll(m.policy, torch.as_tensor(expert.s),
                                expert_actions(expert.action, "cpu")))


def _adam_steps(m) -> int:
    optim = m["optim"] if isinstance(m, dict) else m.policy.optimizer.state_dict()
    return int(next(iter(optim["state"].values()))["step"])


def _full_steps(m) -> int:
    return m.n_epochs * -(-m.rollout_buffer.num_active // m.batch_size)


def _partial_target_kl(m, snap, settings) -> float:
    """A target_kl at which SB3's update stops early after some steps (the buffer's policy is
    already one update old, so the first minibatches start from a nonzero KL)."""
    for target in np.geomspace(1e-4, 1.0, 25):
        _restore(m, snap, **settings, target_kl=float(target))
        PPO.train(m)
        if 0 < _adam_steps(m) - _adam_steps(snap) < _full_steps(m):
            return float(target)
    raise AssertionError("no target_kl stops this update early")


@pytest.mark.sumo
@pytest.mark.parametrize("variant", ["plain", "clip_vf_and_target_kl", "no_adv_norm"])
def test_train_without_bc_is_sb3_ppo_bit_for_bit(filled, variant):
    """bc_coef = 0: MaskedPPO.train and stable_baselines3.PPO.train give the same parameters
    and Adam state, bit for bit, from the same state on the same rollout buffer (also with
    value clipping and approx-KL early stopping, and without advantage normalisation)."""
    run, snap = filled
    m = run.model
    settings = {"bc_coef": 0.0}
    if variant == "clip_vf_and_target_kl":
        settings.update(clip_range_vf=FloatSchedule(0.05),
                        target_kl=_partial_target_kl(m, snap, settings))
    if variant == "no_adv_norm":
        settings.update(normalize_advantage=False)
    try:
        got = []
        for update in (type(m).train, PPO.train):
            _restore(m, snap, **settings)
            update(m)
            got.append((_params(m), m._n_updates, np.random.get_state()[1].copy(),
                        m.logger.name_to_value["train/approx_kl"]))
        (a, na, ra, kla), (b, nb, rb, klb) = got
        assert a.keys() == b.keys()
        for k in a:
            assert torch.equal(a[k], b[k]), k
        assert na == nb and np.array_equal(ra, rb) and kla == klb
        moved = _params(m)["policy.action_net.weight"]
        assert not torch.equal(moved, snap["policy"]["action_net.weight"])
        if variant == "clip_vf_and_target_kl":  # the early stop happened mid-update
            assert 0 < _adam_steps(m) - _adam_steps(snap) < _full_steps(m)
    finally:
        _restore(m, snap, bc_coef=0.5, clip_range_vf=None, target_kl=None,
                 normalize_advantage=True)


@pytest.mark.sumo
def test_bc_term_lowers_the_expert_nll_and_decays(filled, setup):
    """bc_coef > 0 lowers the expert NLL against bc_coef = 0 after a few updates on the same
    buffer; its weight is c · d**u at update u; it draws its pairs from its own generator (the
    global numpy RNG, which orders the minibatches, sees the same draws)."""
    _, cfg, expert = setup
    run, snap = filled
    m = run.model
    start = _nll(m, expert)
    try:
        out = {}
        for coef in (0.0, 10.0):
            _restore(m, snap, bc_coef=coef, bc_decay=0.8)
            m.set_learning_rate(3e-3)  # both arms alike: a few updates show the difference
            weights, losses = [], []
            for _ in range(4):
                m.logger.dump()  # (no outputs) forget the last update's values
                m.train()
                weights.append(m.logger.name_to_value["train/bc_coef"])
                losses.append(m.logger.name_to_value.get("train/bc_loss"))
            out[coef] = (_nll(m, expert), weights, losses, np.random.get_state()[1].copy(),
                         m.bc_rng.bit_generator.state)
        plain, bc = out[0.0], out[10.0]
        assert bc[0] < plain[0] - 0.05 and bc[0] < start, (start, plain[0], bc[0])
        assert plain[1] == [0.0] * 4 and plain[2] == [None] * 4
        u0 = snap["bc_updates"]  # updates the run has done (the fixture's one)
        assert u0 == 1 and bc[1] == pytest.approx([8.0, 6.4, 5.12, 4.096], rel=1e-12)
        assert bc[1] == [10.0 * 0.8 ** u for u in range(u0, u0 + 4)]
        assert all(np.isfinite(v) and v > -20 for v in bc[2])
        assert np.array_equal(plain[3], bc[3])  # same minibatch order
        assert bc[4] != snap["bc_rng"] and plain[4] == snap["bc_rng"]
        assert m.bc_updates == snap["bc_updates"] + 4
    finally:
        _restore(m, snap, bc_coef=0.5, bc_decay=0.8)


@pytest.mark.sumo
def test_resume_with_bc_regulariser_is_exact(setup):
    """1 update + resume + 1 equals 2 updates straight, bit for bit, with bc_coef > 0 and
    bc_decay < 1 (the sampler state and the update count are in the checkpoint)."""
    root, cfg, _ = setup
    straight = train(cfg, run_dir=root / "straight", log=lambda s: None)
    half = train(replace(cfg, updates=1), run_dir=root / "split", log=lambda s: None)
    resumed = train(cfg, resume=half, log=lambda s: None)
    a = load_checkpoint(straight / "checkpoints" / "latest.pt")
    b = load_checkpoint(resumed / "checkpoints" / "latest.pt")
    first = load_checkpoint(straight / "checkpoints" / "update_000001.pt")
    assert a["update"] == b["update"] == 2
    assert first["bc_regulariser"]["updates"] == 1 and a["bc_regulariser"]["updates"] == 2
    assert a["bc_regulariser"] == b["bc_regulariser"]
    assert first["bc_regulariser"]["rng"] != a["bc_regulariser"]["rng"]
    for key in ("policy", "discriminator"):
        assert a[key].keys() == b[key].keys()
        for k in a[key]:
            assert torch.equal(a[key][k], b[key][k]), (key, k)
    sa, sb = a["policy_optimizer"]["state"], b["policy_optimizer"]["state"]
    for k in sa:
        for n in sa[k]:
            assert torch.equal(torch.as_tensor(sa[k][n]), torch.as_tensor(sb[k][n])), (k, n)
    assert a["learning_rate"] == b["learning_rate"]


@pytest.mark.parametrize("text, pattern", [
    ("ppo:\n  bc_coef: -0.1\n", r"ppo\.bc_coef: must be >= 0, got -0\.1"),
    ("ppo:\n  bc_decay: 0\n", r"ppo\.bc_decay: must be in \(0, 1\], got 0"),
    ("ppo:\n  bc_decay: 1.5\n", r"ppo\.bc_decay: must be in \(0, 1\], got 1\.5"),
    ("ppo:\n  bc_batch_size: 0\n", r"ppo\.bc_batch_size: must be >= 1, got 0"),
    ("ppo:\n  bc_coef: .nan\n", r"ppo\.bc_coef: expected a finite number"),
])
def test_bc_settings_out_of_range_refused(tmp_path, text, pattern):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=pattern) as exc:
        load_config(p, TrainConfig)
    msg = str(exc.value)
    assert msg.startswith(f"{p}: ") and "\n" not in msg and len(msg) <= MAX_MESSAGE


def test_bc_defaults_off_and_shipped_config():
    p = PPOConfig()
    assert (p.bc_coef, p.bc_decay, p.bc_batch_size) == (0.0, 1.0, 256)
    from conftest import ROOT

    womd3 = ROOT / "configs" / "experiments" / "womd3"
    reg = load_config(womd3 / "magail_bcreg.yaml", TrainConfig)
    base = load_config(womd3 / "magail_scratch.yaml", TrainConfig)
    assert (reg.ppo.bc_coef, reg.ppo.bc_decay) == (0.1, 0.98)
    assert replace(reg, ppo=replace(reg.ppo, bc_coef=0.0, bc_decay=1.0)) == base
