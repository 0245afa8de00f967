"""Evaluation prepares once: the rollouts of a batch share one env (reset with each rollout's
seed, or one batched env with a world per rollout) and one policy (reseeded per rollout or
per world), and give what a fresh env and a fresh policy per rollout give; the report computes
a scene's log features once."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from conftest import ROOT, WOMD_DIR, tiny_checkpoint
from converters import load_scene
from magail_sumo import agents, policies
from magail_sumo.config import from_dict
from magail_sumo.evaluation import methods, protocol, storage
from magail_sumo.evaluation.realism import CHALLENGE_2025, joint_trajectories, log_replay
from magail_sumo.evaluation.realism.metrics import compute_features, log_features
from magail_sumo.evaluation.report.scoring import LogFeatures, score_pair
from magail_sumo.evaluation.submission import sim_agent_ids
from magail_sumo.models.branched import BranchedSAC
from magail_sumo.models.gameformer import GameFormer
from magail_sumo.sensors.config import ObservationConfig
from magail_sumo.training.config import TrainConfig

SID = "637f20cafde22ff8"
BUNDLE = ROOT / "networks" / SID
SEEDS = [protocol.rollout_seed(0, r) for r in range(3)]
TINY_GF = {"d_model": 16, "num_heads": 2, "fusion_layers": 1, "ff_dim": 32, "modes": 3,
           "levels": 2, "future_steps": 80}


@pytest.fixture(scope="module")
def scene():
    return load_scene(WOMD_DIR / f"{SID}.tfrecord")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A tiny PPO checkpoint trained with the leader feature and behind the gap guard: its
    policy asks evaluation for another env than the default one."""
    path = tmp_path_factory.mktemp("ckpt") / "agent.pt"
    return tiny_checkpoint(path, {"observation": {"leader": True}, "guard": {"kind": "gap"}})


def _gameformer():
    cfg = from_dict(TrainConfig, {"algorithm": "gameformer", "gameformer": {
        "model": TINY_GF, "max_agents": 4, "map_elements": 4, "map_points": 5}})
    torch.manual_seed(0)
    model = GameFormer(cfg.gameformer.model).eval()
    return lambda seed: policies.GameFormerPolicy(model, cfg, "tiny", seed=seed)


def _sac():
    torch.manual_seed(0)
    model = BranchedSAC(6, (3, 4, 5), hidden=(8,))
    obs = ObservationConfig(command=True)
    return lambda seed: policies.SacCheckpointPolicy(model, obs, "tiny", seed=seed)


def _parquet(scene, ro, path) -> bytes:
    storage.write_parquet(path, storage.to_frame(scene, ro, "m"))
    return path.read_bytes()


def _fresh(scene, make) -> tuple:
    """The old way: a new policy and a new env for every rollout."""
    ids = sim_agent_ids(scene)
    runs = [methods.policy_rollout(scene, BUNDLE, make(s), s) for s in SEEDS]
    return methods.as_rollouts(scene, ids, *([r[k] for r in runs] for k in range(3)))


# ------------------------------------------------------------------------------ policy reseed
def _acts(policy, n: int = 3) -> list[np.ndarray]:
    rng = np.random.default_rng(7)
    dim = getattr(policy, "obs_dim", None) or getattr(getattr(policy, "model", None),
                                                      "obs_dim", 3)
    out = []
    for _ in range(n):
        obs = {str(k): rng.normal(size=dim).astype(np.float32) for k in (5, 2, 9)}
        obs["2"][3:6] = (0, 1, 0) if dim >= 6 else obs["2"][3:6]  # a SAC command one-hot
        act = policy.act(obs)
        out.append(np.stack([act[k] for k in sorted(act)]))
    return out


@pytest.mark.parametrize("kind", ["random", "checkpoint", "sac"])
def test_a_reseeded_policy_acts_as_a_fresh_one(kind, checkpoint):
    make = {"random": agents.RandomPolicy,
            "checkpoint": lambda s: policies.make_policy(str(checkpoint), s),
            "sac": _sac()}[kind]
    used = make(11)
    _acts(used)  # its generator has moved on
    used.reseed(SEEDS[1])
    for a, b in zip(_acts(used), _acts(make(SEEDS[1]))):
        np.testing.assert_array_equal(a, b)


def test_a_reseeded_gameformer_draws_as_a_fresh_one():
    make = _gameformer()
    used = make(11)
    used.rng.random(5)
    used.env = object()
    used.reseed(SEEDS[1])
    fresh = make(SEEDS[1])
    assert used.env is None
    np.testing.assert_array_equal(used.rng.random(8), fresh.rng.random(8))


def test_a_policy_without_reseed_is_built_per_rollout(scene):
    class NoReseed:  # e.g. a user's module:factory policy
        def __init__(self, seed):
            self.seed = seed

        def act(self, observations):
            return {}

    built: list[int] = []

    def make(cls):
        return lambda seed: built.append(seed) or cls(seed)

    pr = methods.PolicyRollouts(scene, BUNDLE, make(NoReseed))
    assert [pr.policy_for(s).seed for s in SEEDS] == SEEDS and built == SEEDS
    built.clear()
    pr = methods.PolicyRollouts(scene, BUNDLE, make(agents.RandomPolicy))
    policy = pr.policy_for(SEEDS[0])
    assert all(pr.policy_for(s) is policy for s in SEEDS[1:])
    assert built == SEEDS[:1]  # built once, reseeded after


# ---------------------------------------------------------------------------- env and policy
@pytest.mark.sumo
@pytest.mark.parametrize("spec", ["random", "checkpoint", "correlated"])
def test_simulate_reuses_one_env_and_gives_the_fresh_rollouts(spec, scene, checkpoint, tmp_path,
                                                              env_configs, monkeypatch):
    """The policies act for many worlds at once: the batch's rollouts run in one batched env
    (one world per rollout) and give byte for byte what a fresh env and policy per rollout
    give (with step-to-step correlated noise too, which remembers each agent's past)."""
    if spec == "correlated":
        from magail_sumo import pretrained
        from magail_sumo.agents.noise import NoiseShape

        pretrained.export(checkpoint, "smooth", tmp_path / "reg", noise_scale=0.5,
                          noise_shape=NoiseShape(weights=(1.0, 0.5), correlation=(0.7, 0.5)))
        monkeypatch.setenv(pretrained.ENV_VAR, str(tmp_path / "reg"))
        spec = "pretrained:smooth"
    spec = str(checkpoint) if spec == "checkpoint" else spec
    ro = methods.simulate(scene, spec, range(len(SEEDS)), seed=0, bundle_dir=BUNDLE)
    assert len(env_configs) == 1  # one env for the batch
    fresh = _fresh(scene, lambda s: policies.make_policy(spec, s))
    assert len(env_configs) == 1 + len(SEEDS)
    assert _parquet(scene, ro, tmp_path / "reused.parquet") == \
        _parquet(scene, fresh, tmp_path / "fresh.parquet")


@pytest.mark.sumo
def test_gameformer_rollouts_reuse_the_env_and_policy(scene, tmp_path):
    make = _gameformer()
    ids = sim_agent_ids(scene)
    with methods.PolicyRollouts(scene, BUNDLE, make) as pr:
        runs = [pr.run(s) for s in SEEDS]
        env = pr.env
    reused = methods.as_rollouts(scene, ids, *([r[k] for r in runs] for k in range(3)))
    assert env is not None and env._session is None  # closed with the batch
    assert _parquet(scene, reused, tmp_path / "reused.parquet") == \
        _parquet(scene, _fresh(scene, make), tmp_path / "fresh.parquet")


# ------------------------------------------------------------------------------ log features
def test_log_features_once_per_scene_equal_the_joint_computation(scene, monkeypatch):
    ro = log_replay(scene, 3, protocol.N_STEPS)
    cv = methods.constant_velocity(scene, ro.object_id)
    moved = dataclasses.replace(ro, x=np.repeat(cv[0][None].astype(np.float32), 3, 0),
                                y=np.repeat(cv[1][None].astype(np.float32), 3, 0))
    jt = joint_trajectories(scene, moved)
    jt = dataclasses.replace(jt, n_eval=len(jt.object_id))
    joint = compute_features(scene, jt, CHALLENGE_2025)
    apart = compute_features(scene, jt, CHALLENGE_2025, log_features(scene, jt, CHALLENGE_2025))
    assert joint.values.keys() == apart.values.keys()
    for k in joint.values:
        np.testing.assert_array_equal(joint.values[k], apart.values[k], err_msg=k)

    from magail_sumo.evaluation.report import scoring

    calls = []
    real = scoring.log_features
    monkeypatch.setattr(scoring, "log_features", lambda *a: calls.append(1) or real(*a))
    log = LogFeatures()
    with_log = [score_pair(scene, m, r, log) for m, r in (("a", ro), ("b", moved))]
    assert len(calls) == 1
    without = [score_pair(scene, m, r) for m, r in (("a", ro), ("b", moved))]
    for a, b in zip(with_log, without):
        assert a.error is None and b.error is None
        assert _same(a.row, b.row)
        assert len(a.agent_rows) == len(b.agent_rows)
        assert all(_same(x, y) for x, y in zip(a.agent_rows, b.agent_rows))


def _same(a: dict, b: dict) -> bool:
    """Equal dicts, NaN equal to NaN."""
    return a.keys() == b.keys() and all(
        a[k] == b[k] or (isinstance(a[k], float) and a[k] != a[k] and b[k] != b[k]) for k in a)
