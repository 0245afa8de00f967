"""Training: masked rollout buffer, KL-adaptive lr, (MA)GAIL / BC runs, exact resume, bad input;
algorithms registered by name and dispatched by ``train``; the RNG state helpers."""

from __future__ import annotations

import random
import threading
import types
from dataclasses import replace

import numpy as np
import pytest
import torch
from gymnasium import spaces

from conftest import WOMD_DIR
from magail_sumo.cli.main import main
from magail_sumo.config import ConfigError, from_dict, load_config
from magail_sumo.env.scene_specs import scene_specs
from magail_sumo.expert import record_expert
from magail_sumo.training import algorithms
from magail_sumo.training.config import TrainConfig
from magail_sumo.training.gail.ppo import MaskedRolloutBuffer, adapt_learning_rate
from magail_sumo.training.rng import decode_rng, encode_rng, rng_state, set_rng_state
from magail_sumo.training.trainer import CheckpointError, load_checkpoint, load_policy, train

SCENE = str(WOMD_DIR / "850c48d8bbfa008f.tfrecord")


@pytest.fixture(scope="module")
def setup(tmp_path_factory, bundled_networks):
    root = tmp_path_factory.mktemp("training")
    nets = bundled_networks("850c48d8bbfa008f")
    record_expert(scene_specs([SCENE], nets), root / "expert")
    cfg = from_dict(TrainConfig, {
        "seed": 3, "expert_dir": str(root / "expert"), "out_dir": str(root / "runs"),
        "updates": 4, "checkpoint_every": 2,
        "env": {"max_steps": 30},
        "scenes": {"files": [SCENE], "networks": str(nets)},
        "policy": {"actor_hidden": [16, 16], "critic_hidden": [16, 16]},
        "ppo": {"n_steps": 16, "batch_size": 16, "n_epochs": 2},
        "discriminator": {"epochs": 3, "batch_size": 8, "transformer": {
            "embed_dim": 16, "num_layers": 1, "num_heads": 2, "ff_dim": 32}},
        "bc": {"epochs": 2, "batch_size": 64}})
    return root, cfg


def test_masked_buffer_drops_free_slots():
    obs_space = spaces.Box(-1, 1, (3,), np.float32)
    buf = MaskedRolloutBuffer(4, obs_space, spaces.Box(-1, 1, (2,), np.float32), n_envs=3)
    masks = iter(np.array([[1, 0, 1], [1, 0, 0], [0, 1, 0], [1, 1, 1]], bool))
    buf.mask_source = lambda: next(masks)
    for t in range(4):
        obs = np.full((3, 3), t, np.float32) + np.arange(3)[:, None] * 10
        buf.add(obs, np.zeros((3, 2)), np.zeros(3), np.zeros(3), torch.zeros(3), torch.zeros(3))
    buf.compute_returns_and_advantage(torch.zeros(3), np.zeros(3))
    got = np.concatenate([b.observations[:, 0].numpy() for b in buf.get(2)])
    assert sorted(got.tolist()) == [0, 1, 3, 12, 13, 20, 23]



def test_masked_buffer_minibatches_are_sb3s():
    """The masked buffer gathers its minibatches in torch from the whole rollout; each field is
    SB3's own rollout buffer's minibatch of the same rows, bit for bit."""
    from stable_baselines3.common.buffers import RolloutBuffer

    rng = np.random.default_rng(3)
    spaces_ = (spaces.Box(-1, 1, (3,), np.float32), spaces.Box(-1, 1, (2,), np.float32))
    ours, sb3 = MaskedRolloutBuffer(5, *spaces_, n_envs=4), RolloutBuffer(5, *spaces_, n_envs=4)
    for _ in range(5):
        step = (rng.normal(size=(4, 3)).astype(np.float32), rng.normal(size=(4, 2)),
                rng.normal(size=4), rng.random(4) < 0.2, torch.randn(4), torch.randn(4))
        for buf in (ours, sb3):
            buf.add(*step)
    for buf in (ours, sb3):
        buf.compute_returns_and_advantage(torch.ones(4), np.zeros(4))
    next(ours.get(4)), next(sb3.get(4))  # both flattened
    rows = np.array([17, 2, 9, 9, 0])
    for got, want in zip(ours._get_samples(rows), sb3._get_samples(rows)):
        assert got.dtype == want.dtype and torch.equal(got, want)


def test_info_scan_reads_done_slots_only():
    """MaskedPPO's episode / success bookkeeping keeps what SB3's keeps when, as with a
    Monitor, summaries come with their slot's done, without reading the other slots."""
    from collections import deque

    from magail_sumo.training.gail.ppo import MaskedPPO

    class Loud(dict):
        def get(self, *a):  # a slot whose info must not be read
            raise AssertionError("read a slot that is not done")

    algo = object.__new__(MaskedPPO)
    algo.ep_info_buffer, algo.ep_success_buffer = deque(maxlen=10), deque(maxlen=10)
    infos = [Loud(), {"episode": {"r": 1.0}, "is_success": True}, Loud(),
             {"is_success": False}]
    algo._update_info_buffer(infos, np.array([False, True, False, True]))
    assert list(algo.ep_info_buffer) == [{"r": 1.0}]
    assert list(algo.ep_success_buffer) == [True, False]

def test_kl_rule():
    assert adapt_learning_rate(1e-3, 0.05, 0.01, 1e-5, 1e-2) == 5e-4
    assert adapt_learning_rate(1e-3, 0.001, 0.01, 1e-5, 1e-2) == pytest.approx(1.5e-3)
    assert adapt_learning_rate(1e-3, 0.01, 0.01, 1e-5, 1e-2) == 1e-3
    assert adapt_learning_rate(1e-2, 0.0001, 0.01, 1e-5, 1e-2) == 1e-2


@pytest.mark.sumo
def test_resume_continues_exactly(setup):
    root, cfg = setup
    straight = train(cfg, run_dir=root / "straight", log=lambda s: None)
    half = train(replace(cfg, updates=2), run_dir=root / "split", log=lambda s: None)
    resumed = train(cfg, resume=half, log=lambda s: None)
    a = load_checkpoint(straight / "checkpoints" / "latest.pt")
    b = load_checkpoint(resumed / "checkpoints" / "latest.pt")
    assert a["update"] == b["update"] == 4
    for key in ("policy", "discriminator", "policy_optimizer"):
        sa, sb = a[key], b[key]
        if key == "policy_optimizer":
            sa, sb = sa["state"], sb["state"]
            sa = {f"{k}.{n}": v for k, d in sa.items() for n, v in d.items()}
            sb = {f"{k}.{n}": v for k, d in sb.items() for n, v in d.items()}
        assert sa.keys() == sb.keys()
        for k in sa:
            assert torch.equal(torch.as_tensor(sa[k]), torch.as_tensor(sb[k])), (key, k)
    assert a["learning_rate"] == b["learning_rate"] and a["num_timesteps"] == b["num_timesteps"]
    rec = (straight / "environment.json").read_text()
    assert "git_commit" in rec and "stable-baselines3" in rec
    assert (straight / "config.yaml").is_file() and any((straight / "tb").iterdir())


@pytest.mark.sumo
def test_mlp_gail_and_bc(setup, tmp_path):
    root, cfg = setup
    mlp = replace(cfg, updates=1, discriminator=replace(cfg.discriminator, kind="mlp",
                                                        mlp_hidden=(16,)))
    run = train(mlp, run_dir=tmp_path / "mlp", log=lambda s: None)
    assert load_checkpoint(run / "checkpoints" / "latest.pt")["update"] == 1
    lines = []
    bc = train(replace(cfg, algorithm="bc"), run_dir=tmp_path / "bc", log=lines.append)
    assert any("bc epoch 2" in s for s in lines)
    policy, got = load_policy(bc / "checkpoints" / "latest.pt")
    assert got.algorithm == "bc"
    act, _ = policy.predict(np.zeros((4, 113), np.float32), deterministic=True)
    assert act.shape == (4, 2) and np.all(np.abs(act) <= 1)


@pytest.mark.sumo
def test_bad_config_and_checkpoint(setup, tmp_path, capsys):
    root, cfg = setup
    bad = tmp_path / "bad.yaml"
    bad.write_text("ppo:\n  n_stepz: 3\n")
    with pytest.raises(ConfigError, match=r"ppo\.n_stepz: unknown key"):
        load_config(bad, TrainConfig)
    bad.write_text("discriminator:\n  epochs: many\n")
    with pytest.raises(ConfigError, match=r"discriminator\.epochs: expected an integer"):
        load_config(bad, TrainConfig)
    assert main(["train", "--config", str(bad)]) == 1
    assert "discriminator.epochs" in capsys.readouterr().err
    # corrupt checkpoint: clear error, nothing overwritten
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "latest.pt").write_bytes(b"not a checkpoint")
    (run / "config.yaml").write_text("keep")
    with pytest.raises(CheckpointError, match="corrupt or unreadable"):
        train(cfg, resume=run)
    assert (run / "config.yaml").read_text() == "keep"
    assert sorted(p.name for p in run.rglob("*")) == ["checkpoints", "config.yaml", "latest.pt"]
    # incompatible expert dir named
    seed_layout = replace(cfg, env=replace(cfg.env, observation=replace(
        cfg.env.observation, layout="seed")))
    with pytest.raises(Exception, match="layout mismatch"):
        train(seed_layout, run_dir=tmp_path / "x")


@pytest.mark.sumo
def test_deferred_rewards_equal_per_step_rewards(setup):
    """Training computes the imitation rewards in batched forwards, blocks of steps on a
    background thread while the workers step and the rest after the rollout; they are the
    per-step rewards (frozen discriminator) up to float rounding, with or without blocks ahead."""
    from magail_sumo.expert import ExpertDataset
    from magail_sumo.sensors.observation import observation_names
    from magail_sumo.training.trainer import GailRun

    root, cfg = setup
    expert = ExpertDataset(cfg.expert_dir, observation_names(cfg.env.observation))
    got = []
    for mode in ("ahead", "after", "per_step"):
        torch.manual_seed(0)
        np.random.seed(0)
        run = GailRun(cfg, expert)
        try:
            run.policy.obs_normalizer.update(torch.as_tensor(expert.s))
            ahead = []
            if mode == "ahead":  # blocks of 3 steps (the rollout's n_steps is more)
                run.wrapper.ahead_steps = 3
                take = run.wrapper._rewards_of
                run.wrapper._rewards_of = lambda *a: (ahead.append(
                    threading.current_thread() is not threading.main_thread()), take(*a))[1]
            elif mode == "after":
                run.wrapper.ahead_steps = None
            else:
                run.wrapper.deferred = False
                run.model.rollout_buffer.reward_source = None
            run.run_update()
            if mode == "ahead":  # every full block ran on the thread, the last after
                assert len(ahead) == -(-cfg.ppo.n_steps // 3) and all(ahead[:-1])
                assert not ahead[-1]
            buf = run.model.rollout_buffer
            got.append((buf.rewards.copy(), buf.active.copy(),
                        run.wrapper.pop_reward_stats()))
        finally:
            run.close()
    (r_def, a_def, s_def), *others = got
    for r_other, a_other, s_other in others:
        assert np.array_equal(a_def, a_other) and a_def.any()
        assert np.allclose(r_def, r_other, atol=1e-5) and np.all(r_def[~a_def] == 0)
        assert s_def["agent_steps"] == s_other["agent_steps"]
        assert s_def["imitation_mean"] == pytest.approx(s_other["imitation_mean"], abs=1e-5)
    assert np.abs(r_def[a_def]).max() > 0


def test_rollout_loop_is_sb3s_with_actions_sent_before_booking(setup):
    """MaskedPPO's rollout loop gives SB3's rollout bit for bit, but sends each step's actions
    before it books the step before (the buffer row of step t is added after step t+1 was
    sent, while the workers step)."""
    from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm

    from magail_sumo.expert import ExpertDataset
    from magail_sumo.sensors.observation import observation_names
    from magail_sumo.training.trainer import GailRun

    root, cfg = setup
    expert = ExpertDataset(cfg.expert_dir, observation_names(cfg.env.observation))
    got = []
    for loop in ("ours", "sb3"):
        torch.manual_seed(0)
        np.random.seed(0)
        run = GailRun(cfg, expert)
        try:
            run.policy.obs_normalizer.update(torch.as_tensor(expert.s))
            model, sent, order = run.model, [0], []
            if loop == "sb3":
                model.collect_rollouts = types.MethodType(OnPolicyAlgorithm.collect_rollouts, model)
            send = run.wrapper.step_async
            run.wrapper.step_async = lambda a: (sent.__setitem__(0, sent[0] + 1), send(a))[1]
            add = model.rollout_buffer.add
            model.rollout_buffer.add = lambda *a, **k: (order.append(sent[0]), add(*a, **k))[1]
            run.run_update()
            buf = model.rollout_buffer
            got.append([getattr(buf, f).copy() for f in (
                "observations", "actions", "rewards", "episode_starts", "values", "log_probs",
                "advantages", "returns", "active")])
            n = cfg.ppo.n_steps
            if loop == "ours":  # row t booked after the actions of t + 1 went out
                assert order == [min(t + 2, n) for t in range(n)]
            else:
                assert order == [t + 1 for t in range(n)]
        finally:
            run.close()
    for a, b in zip(*got):
        assert np.array_equal(a, b)
    assert got[0][-1].any() and np.abs(got[0][2]).max() > 0


@pytest.mark.sumo
def test_resume_refuses_a_changed_config(setup, tmp_path):
    from magail_sumo.config import to_dict
    from magail_sumo.training.trainer import _check_resume_config

    _, cfg = setup
    saved = to_dict(cfg)
    # run length, worker timeout and pinning change neither results nor state
    _check_resume_config(replace(cfg, updates=9, scenes=replace(
        cfg.scenes, pin_workers=True, worker_timeout_s=5.0)), saved, tmp_path)
    changed = replace(cfg, ppo=replace(cfg.ppo, n_epochs=cfg.ppo.n_epochs + 1), seed=cfg.seed + 1)
    with pytest.raises(ConfigError, match=r"differs from the run's in ppo\.n_epochs, seed"):
        _check_resume_config(changed, saved, tmp_path)


@pytest.mark.sumo
def test_cli_seed_overrides_the_config(setup, tmp_path):
    import yaml

    from magail_sumo.config import to_dict

    _, cfg = setup
    path = tmp_path / "bc.yaml"
    path.write_text(yaml.safe_dump(to_dict(replace(cfg, algorithm="bc"))))
    run = tmp_path / "run"
    assert main(["train", "--config", str(path), "--seed", "7", "--run-dir", str(run)]) == 0
    assert yaml.safe_load((run / "config.yaml").read_text())["seed"] == 7
    assert load_checkpoint(run / "checkpoints" / "latest.pt")["config"]["seed"] == 7


@pytest.mark.sumo
def test_training_without_the_sumo_mirror_is_the_same(setup, tmp_path):
    """``env.sumo_mirror: false`` (log background: SUMO skipped) trains to the same checkpoint,
    tensor for tensor, on random windows of a real scene."""
    root, cfg = setup
    base = replace(cfg, updates=2, env=replace(cfg.env, start_window="random", max_steps=20))
    runs = [train(replace(base, env=replace(base.env, sumo_mirror=m)), run_dir=tmp_path / str(m),
                  log=lambda s: None) for m in (True, False)]
    a, b = (load_checkpoint(r / "checkpoints" / "latest.pt") for r in runs)
    assert a["num_timesteps"] == b["num_timesteps"] > 0
    for key in ("policy", "discriminator"):
        assert a[key].keys() == b[key].keys()
        for k in a[key]:
            assert torch.equal(torch.as_tensor(a[key][k]), torch.as_tensor(b[key][k])), (key, k)


def test_rollout_forward_evaluates_occupied_slots_only():
    """A rollout forward over a whole vector-env observation evaluates the occupied slots
    alone: their mean actions, values and log-probabilities are those of a forward over them,
    a free slot gets 0; any other batch is evaluated whole."""
    from magail_sumo.models.policies import TanhGaussianPolicy

    torch.manual_seed(0)
    obs_space = spaces.Box(-np.inf, np.inf, (7,), np.float32)
    policy = TanhGaussianPolicy(obs_space, spaces.Box(-1.0, 1.0, (2,), np.float32),
                                lambda _: 3e-4)
    mask = np.array([True, False, True, True, False, False])
    policy.set_scene_layout(np.array([0, 0, 0, 1, 1, 1]), lambda: mask)
    obs = torch.randn(6, 7)
    with torch.no_grad():
        acts, values, logp = policy(obs, deterministic=True)
        policy.set_scene_layout(None)
        ref = policy(obs[torch.as_tensor(np.flatnonzero(mask))], deterministic=True)
        whole = policy(obs, deterministic=True)
    for got, want in zip((acts, values, logp), ref):
        torch.testing.assert_close(got[torch.as_tensor(mask)], want)
        assert torch.all(got[torch.as_tensor(~mask)] == 0)
    assert torch.all(whole[1][torch.as_tensor(~mask)] != 0)  # no layout: every row evaluated


# ------------------------------------------------------------------ algorithms by name, RNG helpers
def test_builtin_algorithms_are_registered():
    assert set(algorithms.REGISTRY) >= {"gail", "bc", "sac", "sac_gail", "gameformer"}
    assert algorithms.get("gail").adversarial and algorithms.get("sac_gail").adversarial
    assert not algorithms.get("bc").adversarial
    for alg in algorithms.REGISTRY.values():  # every entry point resolves to a function
        assert callable(alg.run_function()), alg.name
    with pytest.raises(KeyError, match="unknown algorithm 'nope'"):
        algorithms.get("nope")


def test_a_registered_algorithm_is_configured_and_run_by_train(tmp_path, monkeypatch):
    from magail_sumo.training import trainer

    calls = []

    def run(cfg, run_dir, ckpt, log, progress):
        calls.append((cfg.algorithm, run_dir, ckpt))
        log("toy ran")
        return run_dir

    monkeypatch.setitem(algorithms.REGISTRY, "toy",
                        algorithms.Algorithm("toy", f"{__name__}:_unused", adversarial=True))
    monkeypatch.setattr(algorithms.Algorithm, "run_function", lambda self: run)
    with pytest.raises(ConfigError, match="algorithm"):
        from_dict(TrainConfig, {"algorithm": "toy2"})
    cfg = from_dict(TrainConfig, {"algorithm": "toy", "out_dir": str(tmp_path),
                                  "discriminator": {"kind": "mlp"}})
    lines = []
    out = trainer.train(cfg, log=lines.append)
    assert calls == [("toy", out, None)] and lines == ["toy ran"]
    assert out.parent == tmp_path and out.name.startswith("toy-mlp-seed0-")  # adversarial name


def test_rng_round_trip_is_exact():
    random.seed(1), np.random.seed(2), torch.manual_seed(3)
    np.random.normal(size=3)  # leaves a cached gaussian in numpy's legacy state
    saved = rng_state()
    back = decode_rng(encode_rng(saved))
    draws = (random.random(), np.random.normal(size=4), torch.rand(4))
    set_rng_state(back)
    again = (random.random(), np.random.normal(size=4), torch.rand(4))
    assert draws[0] == again[0] and np.array_equal(draws[1], again[1])
    assert torch.equal(draws[2], again[2])
    with pytest.raises((ValueError, TypeError)):
        decode_rng({**encode_rng(saved), "numpy": ["MT19937", torch.zeros(3), 0, 0, 0.0]})


def test_progress_reports_the_env_steps_of_each_update_and_the_updates(setup, tmp_path):
    """``progress`` hears every behavioural-cloning epoch, every env step of each update
    (``ppo.n_steps`` of them, counting anew per update) and every update."""
    root, cfg = setup
    calls = []
    train(replace(cfg, updates=2), run_dir=tmp_path / "run", log=lambda s: None,
          progress=lambda *c: calls.append(c))
    steps = [done for phase, done, total in calls if phase == "steps"]
    assert {total for phase, _, total in calls if phase == "steps"} == {cfg.ppo.n_steps}
    assert steps == list(range(1, cfg.ppo.n_steps + 1)) * 2
    assert [c for c in calls if c[0] == "updates"] == [("updates", 1, 2), ("updates", 2, 2)]
    assert [c[1] for c in calls if c[0] == "bc"] == [1, 2]
