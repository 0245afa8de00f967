"""``magail_sumo.agents`` and ``magail_sumo.policies`` (issue 11): the policy registry (checkpoint
loaders by algorithm, user ``module:function`` entry points), the one rollout loop, and evaluation's
policy rollouts taking each agent's pose from the env (a checkpoint trained with the seed's
``steer_throttle`` action layout rolls out to the poses the env produced)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from conftest import ROOT, WOMD_DIR
from magail_sumo import agents, policies
from magail_sumo.policies import registry
from magail_sumo.errors import MagailSumoError

SID = "850c48d8bbfa008f"


def test_agents_and_the_cli_front_import_no_training():
    """The agents layer sits below training (no trainer, no torch), and the CLI imports a
    command's stack only when that command runs (``magail-sumo inspect`` starts fast)."""
    code = ("import sys, magail_sumo.agents, magail_sumo.cli.main; "
            "bad = sorted(m for m in sys.modules if m.startswith(('magail_sumo.training', "
            "'magail_sumo.policies')) or m in ('torch', 'libsumo')); assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


class _Marker:
    def __init__(self, path, seed, deterministic):
        self.path, self.seed, self.deterministic = path, seed, deterministic

    def act(self, observations):
        return {}


def custom_loader(path, seed, deterministic=False):
    """A loader registered by ``module:function`` (this test module)."""
    return _Marker(path, seed, deterministic)


def test_checkpoint_loaders_by_algorithm(tmp_path, monkeypatch):
    """``.pt`` files go to the loader registered for the algorithm they record; a lazy
    ``module:function`` entry point is imported when used; unknown algorithms and unreadable
    files go to the default loader, which names the problem."""
    monkeypatch.syspath_prepend(str(ROOT / "tests"))
    ckpt = tmp_path / "run.pt"
    torch.save({"format": "x", "config": {"algorithm": "myalgo"}, "policy": {}, "update": 0},
               ckpt)
    assert registry.checkpoint_algorithm(ckpt) == "myalgo"
    monkeypatch.setitem(policies.CHECKPOINT_LOADERS, "myalgo", "test_agents:custom_loader")
    pol = policies.make_policy(str(ckpt), 7, deterministic=True)
    assert isinstance(pol, _Marker) and (pol.seed, pol.deterministic) == (7, True)
    policies.register_checkpoint_loader("myalgo", custom_loader)
    assert policies.make_policy(str(ckpt), 3).seed == 3
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    assert registry.checkpoint_algorithm(bad) is None
    with pytest.raises(MagailSumoError, match="bad.pt: corrupt or unreadable checkpoint"):
        policies.make_policy(str(bad), 0)
    monkeypatch.setitem(policies.CHECKPOINT_LOADERS, "myalgo", "no_such_module:f")
    with pytest.raises(agents.PolicyError, match="run.pt: could not be created"):
        policies.make_policy(str(ckpt), 0)


class _Env:
    """A stand-in env (PettingZoo parallel API): agents "1" and "2", "2" leaves after 2 steps."""

    def __init__(self) -> None:
        self.t, self.agents, self.scene = 0, [], "scene"

    def reset(self, seed=None):
        self.t, self.agents = 0, ["1", "2"]
        return {a: np.zeros(1) for a in self.agents}, {}

    def step(self, actions):
        self.t += 1
        stepped = list(self.agents)
        if self.t == 2:
            self.agents = ["1"]
        obs = {a: np.full(1, self.t) for a in stepped}
        done = {a: a not in self.agents for a in stepped}
        return obs, {a: 0.0 for a in stepped}, done, dict.fromkeys(stepped, False), \
            {a: {"state": (self.t, 0.0, 0.0, 1.0)} for a in stepped}


class _Recorder:
    def __init__(self) -> None:
        self.begun, self.seen = None, []

    def begin(self, scene, env) -> None:
        self.begun = scene

    def act(self, observations):
        self.seen.append(sorted(observations))
        return {a: np.zeros(2, np.float32) for a in observations}


def test_rollout_loop():
    env, pol, steps = _Env(), _Recorder(), []
    n = agents.rollout(env, pol, steps.append, seed=1, max_steps=4)
    assert n == 4 and pol.begun == "scene" and len(steps) == 4
    assert [s.t for s in steps] == [0, 1, 2, 3]
    assert steps[0].agents == ["1", "2"] and steps[2].agents == ["1"]
    assert steps[1].terminations == {"1": False, "2": True}
    assert pol.seen[2] == ["1", "2"]  # acts on what the env observed (the leaving agent too)
    assert steps[3].infos["1"]["state"][0] == 4
    resets = []
    assert agents.rollout(_Env(), _Recorder(), max_steps=2,
                          on_reset=lambda obs, infos: resets.append(sorted(obs))) == 2
    assert resets == [["1", "2"]]


def _seed_layout_checkpoint(tmp_path):
    """A small untrained checkpoint of a run with ``env.action_layout: steer_throttle`` whose
    mean action is clear: throttle (2nd entry) on, steering (1st) small."""
    from magail_sumo.config import from_dict, to_dict
    from magail_sumo.training.config import TrainConfig
    from magail_sumo.training.trainer import CHECKPOINT_FORMAT, make_policy

    cfg = from_dict(TrainConfig, {"seed": 3, "env": {"action_layout": "steer_throttle"},
                                  "policy": {"actor_hidden": [8], "critic_hidden": [8]}})
    torch.manual_seed(3)
    net = make_policy(cfg)
    with torch.no_grad():
        net.action_net.bias.copy_(torch.tensor([0.1, 1.5]))
    ckpt = tmp_path / "seed_layout.pt"
    torch.save({"format": CHECKPOINT_FORMAT, "update": 0, "config": to_dict(cfg),
                "policy": net.state_dict()}, ckpt)
    return ckpt


def test_checkpoint_brings_its_action_layout(tmp_path):
    """Evaluation's env takes a checkpoint's action layout (the policy's ``action_layout``); a
    caller naming another env is refused."""
    from magail_sumo.env import EnvConfig
    from magail_sumo.policies import load_checkpoint_policy
    from magail_sumo.training.trainer import CheckpointError

    ckpt = _seed_layout_checkpoint(tmp_path)
    assert policies.make_policy(str(ckpt), 0).action_layout == "steer_throttle"
    with pytest.raises(CheckpointError, match="env.action_layout: trained 'steer_throttle'"):
        load_checkpoint_policy(ckpt, target=EnvConfig())


@pytest.mark.sumo
def test_checkpoint_action_layout_rolls_out_to_the_env_poses(tmp_path, bundled_networks):
    """A checkpoint trained with ``env.action_layout: steer_throttle`` drives evaluation's env in
    that layout, and the rollout holds the poses the env gave its agents. (Evaluation used to
    re-derive the poses with the default layout: they were another vehicle's motion.)"""
    from converters import load_scene
    from magail_sumo.env import EnvConfig, SumoDrivingEnv
    from magail_sumo.evaluation import methods, protocol

    scene = load_scene(WOMD_DIR / f"{SID}.tfrecord")
    bundle = bundled_networks.bundle(SID)
    ckpt = _seed_layout_checkpoint(tmp_path)

    ro = methods.simulate(scene, str(ckpt), [0], seed=0, bundle_dir=bundle, deterministic=True)
    # the same policy driving the env directly: the poses the env produced
    cur = scene.current_time_index
    env = SumoDrivingEnv(scene, bundle, EnvConfig(
        controlled="all", start_step=cur, max_steps=protocol.N_STEPS, terminate_on=(),
        end_of_life=False, action_layout="steer_throttle"))
    policy = policies.make_policy(str(ckpt), protocol.rollout_seed(0, 0), deterministic=True)
    col = {int(i): k for k, i in enumerate(ro.object_id)}
    checked = 0
    try:
        obs, _ = env.reset(seed=protocol.rollout_seed(0, 0))
        while env.agents:
            t, stepped = env.t - cur, set(env.agents)  # t: column of log step env.t + 1
            obs, *_ = env.step(policy.act(obs))
            st = env.agent_states()
            for k, name in enumerate(st.names):
                if name not in stepped or int(name) not in col:  # joined now / no sim agent
                    continue
                a = col[int(name)]
                want = (st.state.x[k], st.state.y[k], st.state.yaw[k])
                got = (ro.x[0, a, t], ro.y[0, a, t], ro.heading[0, a, t])
                assert np.allclose(got[:2], np.float32(want[:2]), atol=1e-3), (name, t)
                assert abs(np.angle(np.exp(1j * (got[2] - want[2])))) < 1e-3, (name, t)
                checked += 1
    finally:
        env.close()
    assert checked > 100
