"""Command-branched SAC (issue 15, items 5-7): branched heads, collision share of batches,
absorbing states, task reward, route command feature, train / resume through ``train()`` and
evaluation of a SAC checkpoint."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from conftest import WOMD_DIR
from magail_sumo.config import ConfigError, FieldError, from_dict
from magail_sumo.models.branched import BranchedMLP, BranchedSAC
from magail_sumo.sensors.command import LEFT, RIGHT, STRAIGHT, RouteCommands
from magail_sumo.sensors.observation import COMMAND_NAMES, ObservationConfig, observation_names
from magail_sumo.training.config import TrainConfig
from magail_sumo.training.sac.config import TaskRewardConfig
from magail_sumo.training.sac.buffer import ReplayBuffer, collision_count, sample_batch
from magail_sumo.training.sac.transitions import (buffer_rows, step_transitions,
                                                  task_reward)

SCENE = str(WOMD_DIR / "850c48d8bbfa008f.tfrecord")
CMD_OBS = ObservationConfig(command=True)
NAMES = observation_names(CMD_OBS)
F = len(NAMES)


def _obs(n: int, command: np.ndarray) -> np.ndarray:
    x = np.random.default_rng(0).normal(size=(n, F)).astype(np.float32)
    cols = [NAMES.index(c) for c in COMMAND_NAMES]
    x[:, cols] = 0.0
    x[np.arange(n), np.asarray(cols)[command]] = 1.0
    return x


def test_branched_heads_select_by_command():
    torch.manual_seed(0)
    net = BranchedMLP(5, 2, (8,))
    x = torch.randn(6, 5)
    cmd = torch.tensor([0, 1, 2, 0, 1, 2])
    out = net(x, cmd)
    h = net.trunk(x)
    for i in range(6):
        k = int(cmd[i])
        assert torch.allclose(out[i], h[i] @ net.head_weight[k] + net.head_bias[k])
    assert not torch.allclose(net(x, torch.zeros(6, dtype=torch.long)), out)
    # samples of command LEFT only: the other heads get exactly zero gradient
    net(x, torch.full((6,), LEFT)).pow(2).sum().backward()
    assert net.head_weight.grad[LEFT].abs().sum() > 0
    assert torch.count_nonzero(net.head_weight.grad[[STRAIGHT, RIGHT]]) == 0
    assert torch.count_nonzero(net.head_bias.grad[[STRAIGHT, RIGHT]]) == 0


def test_sac_model_reads_the_command_from_the_observation():
    torch.manual_seed(0)
    cols = tuple(NAMES.index(c) for c in COMMAND_NAMES)
    model = BranchedSAC(F, cols, hidden=(8,))
    x = np.concatenate([_obs(3, np.array([LEFT, STRAIGHT, RIGHT])), np.zeros((3, 1))], 1)
    xt = torch.as_tensor(x, dtype=torch.float32)
    assert model.command(xt).tolist() == [LEFT, STRAIGHT, RIGHT]
    mu, _ = model.dist(xt)
    # the same observation with another command one-hot uses another head
    y = xt.clone()
    y[:, list(cols)] = torch.tensor([0.0, 0.0, 1.0])
    mu2, _ = model.dist(y)
    assert torch.allclose(mu[2], mu2[2]) and not torch.allclose(mu[0], mu2[0])
    # a straight-command batch trains only the straight heads of actor, Q and V
    s = torch.as_tensor(np.concatenate([_obs(4, np.full(4, STRAIGHT)), np.zeros((4, 1))], 1),
                        dtype=torch.float32)
    a, logp = model.sample(s)
    q1, q2 = model.q(s, a)
    (q1 + q2 + logp + model.v(s)).sum().backward()
    for net in (model.actor, model.q1, model.q2, model.value):
        g = net.head_weight.grad
        assert g[STRAIGHT].abs().sum() > 0 and torch.count_nonzero(g[[LEFT, RIGHT]]) == 0
    assert a.abs().max() <= 1.0 and torch.isfinite(logp).all()



def test_sac_act_scales_the_sampled_noise():
    """``act(noise_scale=k)`` is ``tanh(mu + k·std·eps)`` with the draws of :meth:`sample`: 1
    is ``sample``'s action bit for bit, 0 the mean's tanh (evaluate --noise-scale on a SAC
    checkpoint)."""
    torch.manual_seed(1)
    cols = tuple(NAMES.index(c) for c in COMMAND_NAMES)
    model = BranchedSAC(F, cols, hidden=(8,))
    x = torch.as_tensor(np.concatenate([_obs(5, np.full(5, STRAIGHT)), np.zeros((5, 1))], 1),
                        dtype=torch.float32)

    def act(k: float) -> torch.Tensor:
        with torch.no_grad():
            return model.act(x, generator=torch.Generator().manual_seed(7), noise_scale=k)

    with torch.no_grad():
        sampled = model.sample(x, torch.Generator().manual_seed(7))[0]
        mu, std = model.dist(x)
    eps = torch.randn(mu.shape, generator=torch.Generator().manual_seed(7))
    assert torch.equal(act(1.0), sampled)
    torch.testing.assert_close(act(0.0), torch.tanh(mu))
    for k in (0.25, 0.5):
        torch.testing.assert_close(act(k), torch.tanh(mu + k * std * eps))
    assert not torch.allclose(act(0.25), act(0.5))

def _fill(buf: ReplayBuffer, n: int, reward: float) -> None:
    buf.add(obs=np.zeros((n, 4)), action=np.zeros((n, 2)), reward=np.full(n, reward),
            next_obs=np.zeros((n, 4)), done=np.zeros(n))


def test_collision_share_is_exact_per_batch():
    main, col = ReplayBuffer(100, 4), ReplayBuffer(100, 4)
    _fill(main, 60, 1.0)
    _fill(col, 5, -1.0)
    rng = np.random.default_rng(0)
    # fewer collision transitions than the share asks: none from that buffer
    assert collision_count(50, 0.2, 5) == 0
    assert (sample_batch(main, col, 50, 0.2, rng)["reward"] == 1).all()
    _fill(col, 20, -1.0)
    for _ in range(5):
        b = sample_batch(main, col, 50, 0.2, rng)
        assert b["reward"].shape == (50,) and int((b["reward"] == -1).sum()) == 10
    assert int((sample_batch(main, col, 64, 0.2, rng)["reward"] == -1).sum()) == 12
    assert int((sample_batch(main, col, 50, 0.0, rng)["reward"] == -1).sum()) == 0
    # ring buffer: oldest overwritten, state round trip
    _fill(main, 70, 2.0)
    assert len(main) == 100 and main.pos == 30
    copy = ReplayBuffer(100, 4)
    copy.load_state_dict(main.state_dict())
    assert torch.equal(copy.data["reward"], main.data["reward"]) and copy.pos == 30


def test_free_slots_never_enter_and_absorbing_states():
    last = np.arange(5 * F, dtype=np.float32).reshape(5, F)
    obs = last + 1000.0
    term = {i: np.full(F, -float(i), np.float32) for i in range(5)}
    acts = np.arange(10, dtype=np.float32).reshape(5, 2)
    acted = np.array([True, True, True, False, True])
    dones = np.array([True, True, False, True, True])
    infos = [{"terminal_observation": term[0], "TimeLimit.truncated": False,
              "reason": "collision"},
             {"terminal_observation": term[1], "TimeLimit.truncated": True,
              "reason": "end_of_life"},
             {}, {},  # slot 3: free, handed to a new agent (done, no terminal observation)
             {"terminal_observation": term[4], "TimeLimit.truncated": False,
              "reason": "destination"}]
    tr = step_transitions(last, acts, obs, dones, infos, acted)
    assert tr.slots.tolist() == [0, 1, 2, 4]
    assert tr.terminated.tolist() == [True, False, False, True]
    assert tr.truncated.tolist() == [False, True, False, False]
    assert np.array_equal(tr.next_obs[1], term[1]) and np.array_equal(tr.next_obs[2], obs[2])
    assert tr.events["collision"].tolist() == [True, False, False, False]
    r = np.array([1.0, 2.0, 3.0, 4.0], np.float32)
    # task SAC: terminations end the return (done 1), the collision goes to its buffer
    main, col = buffer_rows(tr, r, absorbing=False, absorbing_reward=0.5)
    assert col["reward"].tolist() == [1.0] and col["done"].tolist() == [1.0]
    assert main["reward"].tolist() == [2.0, 3.0, 4.0] and main["done"].tolist() == [0, 0, 1]
    assert (main["obs"][:, F] == 0).all() and np.array_equal(main["next_obs"][0, :F], term[1])
    # GAIL: terminated agents lead to the absorbing state, which loops on itself
    main, col = buffer_rows(tr, r, absorbing=True, absorbing_reward=0.5)
    absorbing = np.zeros(F + 1, np.float32)
    absorbing[F] = 1.0
    assert col["done"].tolist() == [0.0] and np.array_equal(col["next_obs"][0], absorbing)
    assert main["reward"].tolist() == [2.0, 3.0, 4.0, 0.5, 0.5]
    assert (main["done"] == 0).all()
    assert np.array_equal(main["next_obs"][2], absorbing)  # destination: terminated
    assert np.array_equal(main["next_obs"][0, :F], term[1])  # truncated: bootstraps
    for k in (3, 4):
        assert np.array_equal(main["obs"][k], absorbing)
        assert np.array_equal(main["next_obs"][k], absorbing)
        assert (main["action"][k] == 0).all()


def test_task_reward_terms():
    w = TaskRewardConfig(progress=0.5, destination=2.0, collision=10.0, off_road=5.0,
                         red_light=3.0, comfort=1.0)
    ix = {n: NAMES.index(n) for n in ("dest_distance", "prev_accel", "prev_steer")}
    s = np.zeros((5, F), np.float32)
    s2 = np.zeros((5, F), np.float32)
    s[:, ix["dest_distance"]] = 20.0
    s2[:, ix["dest_distance"]] = [18.0, 20.0, 21.0, 20.0, 20.0]
    s[:, ix["prev_accel"]] = [0.0, 0.5, 0.0, 0.0, 0.0]
    a = np.zeros((5, 2), np.float32)
    a[1] = [0.0, 0.5]  # accel change -0.5, steer change +0.5
    ev = {"collision": np.array([0, 0, 0, 1, 0], bool),
          "destination": np.array([0, 0, 0, 0, 1], bool),
          "off_road": np.array([0, 0, 1, 0, 0], bool)}
    r = task_reward(s, a, s2, ev, w, NAMES)
    assert r.tolist() == pytest.approx([1.0, -0.5, -0.5 - 5.0, -10.0, 2.0])
    ev = {"red_light": np.array([1, 0, 0, 0, 0], bool)}
    assert task_reward(s, a, s2, ev, w, NAMES)[0] == pytest.approx(1.0 - 3.0)


def test_route_command_of_hand_made_routes():
    t = np.arange(40)
    # three tracks at 1 m per step: straight east, turning left (to north), turning right
    ang = np.clip((t - 10) / 10, 0, 1) * (np.pi / 2)
    xs = np.stack([t * 1.0, np.cumsum(np.cos(ang)), np.cumsum(np.cos(-ang))]).astype(np.float32)
    ys = np.stack([0 * t, np.cumsum(np.sin(ang)), np.cumsum(np.sin(-ang))]).astype(np.float32)
    heading = np.stack([0 * ang, ang, -ang]).astype(np.float32)
    tracks = SimpleNamespace(x=xs, y=ys, heading=heading, valid=np.ones((3, 40), bool))
    rc = RouteCommands.build(tracks, lookahead=30.0)
    rows = np.array([0, 1, 2])
    got = rc.commands(rows, xs[:, 2], ys[:, 2])
    assert got.argmax(1).tolist() == [STRAIGHT, LEFT, RIGHT]
    # past the turn (and near the route's end) the command is straight again
    assert rc.commands(rows, xs[:, 30], ys[:, 30]).argmax(1).tolist() == [STRAIGHT] * 3
    # the feature is off by default: the default layout keeps its 113 values
    assert len(observation_names()) == 113 and F == 116 and NAMES[-3:] == COMMAND_NAMES


def test_sac_config_checks():
    with pytest.raises((ConfigError, FieldError), match="env.observation.command"):
        from_dict(TrainConfig, {"algorithm": "sac"})
    base = {"algorithm": "sac", "env": {"observation": {"command": True}}}
    cfg = from_dict(TrainConfig, base)
    assert cfg.sac.collision_share == 0.2 and cfg.sac.task_reward.collision == 10.0
    for key, value in (("collision_share", 1.0), ("gamma", 1.0), ("tau", 0.0),
                       ("batch_size", 0), ("lr_gamma", 1.5), ("buffer_size", 10)):
        with pytest.raises((ConfigError, FieldError), match=f"sac.{key}|{key}"):
            from_dict(TrainConfig, {**base, "sac": {key: value}})
    with pytest.raises((ConfigError, FieldError), match="task_reward.comfort|comfort"):
        from_dict(TrainConfig, {**base, "sac": {"task_reward": {"comfort": -1}}})


# ----------------------------------------------------------------------------- real runs
@pytest.fixture(scope="module")
def sac_setup(tmp_path_factory, bundled_networks):
    from magail_sumo.env.scene_specs import scene_specs
    from magail_sumo.expert import record_expert

    root = tmp_path_factory.mktemp("sac")
    nets = bundled_networks("850c48d8bbfa008f")
    record_expert(scene_specs([SCENE], nets), root / "expert", observation=CMD_OBS)
    cfg = from_dict(TrainConfig, {
        "algorithm": "sac", "seed": 5, "expert_dir": str(root / "expert"),
        "out_dir": str(root / "runs"), "updates": 4, "checkpoint_every": 2,
        "env": {"max_steps": 30, "observation": {"command": True}},
        "scenes": {"files": [SCENE], "networks": str(nets)},
        "discriminator": {"kind": "mlp", "epochs": 2, "batch_size": 8, "mlp_hidden": [16]},
        "sac": {"hidden": [16, 16], "buffer_size": 500, "batch_size": 16,
                "learning_starts": 8, "train_freq": 4, "gradient_steps": 2, "lr_step": 3}})
    return root, cfg


def _equal_states(a, b, path=""):
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and torch.equal(a, b), path
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            _equal_states(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _equal_states(x, y, f"{path}[{i}]")
    else:
        assert a == b, path


@pytest.mark.sumo
@pytest.mark.parametrize("algorithm", ["sac", "sac_gail"])
def test_train_and_resume_exactly(sac_setup, algorithm):
    from magail_sumo.training.trainer import load_checkpoint, train

    root, cfg = sac_setup
    cfg = replace(cfg, algorithm=algorithm)
    lines: list[str] = []
    straight = train(cfg, run_dir=root / f"{algorithm}-straight", log=lines.append)
    assert any("Q loss" in s for s in lines)
    half = train(replace(cfg, updates=2), run_dir=root / f"{algorithm}-half", log=lambda s: None)
    resumed = train(cfg, resume=half, log=lambda s: None)
    a = load_checkpoint(straight / "checkpoints" / "latest.pt")
    b = load_checkpoint(resumed / "checkpoints" / "latest.pt")
    assert a["update"] == b["update"] == 4 and a["config"]["algorithm"] == algorithm
    assert len(a["buffers"]["main"]["reward"]) > 0
    for key in ("policy", "sac", "buffers", "sampler_rng", "last_obs", "transitions",
                *(("discriminator", "disc_trainer") if algorithm == "sac_gail" else ())):
        _equal_states(a[key], b[key], key)
    # StepLR (3 gradient steps) has decayed the learning rates
    lr = a["sac"]["optimizers"]["actor"]["param_groups"][0]["lr"]
    assert lr < cfg.sac.learning_rate


@pytest.mark.sumo
def test_evaluate_sac_checkpoint(sac_setup, tmp_path):
    from magail_sumo.evaluation.runner import evaluate
    from magail_sumo.policies import make_policy
    from magail_sumo.policies import SacCheckpointPolicy
    from magail_sumo.training.trainer import CheckpointError, load_policy, train

    root, cfg = sac_setup
    run = train(replace(cfg, updates=2), run_dir=tmp_path / "run", log=lambda s: None)
    ckpt = run / "checkpoints" / "latest.pt"
    policy = make_policy(str(ckpt), seed=0)
    assert isinstance(policy, SacCheckpointPolicy) and policy.observation.command
    acts = policy.act({"1": np.zeros(F, np.float32), "2": np.zeros(F, np.float32)})
    assert set(acts) == {"1", "2"} and all(np.abs(v).max() <= 1 for v in acts.values())
    with pytest.raises(CheckpointError, match="SAC"):
        load_policy(ckpt)
    res = evaluate([SCENE], str(ckpt), tmp_path / "eval", n_rollouts=1, baselines=(),
                   workers=1, networks=Path(cfg.scenes.networks), name="sac")
    files = list((tmp_path / "eval" / "rollouts" / "sac").glob("*.parquet"))
    assert len(files) == 1, res


@pytest.mark.sumo
def test_resume_without_buffers_is_approximate(sac_setup, tmp_path):
    from magail_sumo.training.trainer import load_checkpoint, train

    root, cfg = sac_setup
    cfg = replace(cfg, sac=replace(cfg.sac, save_buffers=False))
    half = train(replace(cfg, updates=2), run_dir=tmp_path / "half", log=lambda s: None)
    assert load_checkpoint(half / "checkpoints" / "latest.pt")["buffers"] is None
    lines: list[str] = []
    train(replace(cfg, updates=3), resume=half, log=lines.append)
    assert any("approximate resume" in s for s in lines)
    b = load_checkpoint(half / "checkpoints" / "latest.pt")
    assert b["update"] == 3 and b["transitions"] < b["env_counters"][0]
