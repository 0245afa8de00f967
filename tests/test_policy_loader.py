"""Training checkpoints as `magail-sumo evaluate --policy RUN/checkpoints/latest.pt` policies."""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from conftest import WOMD_DIR
from converters import load_scene
from magail_sumo import agents, policies
from magail_sumo.cli.main import main
from magail_sumo.config import from_dict
from magail_sumo.env.config import EnvConfig
from magail_sumo.env.scene_specs import scene_specs
from magail_sumo.evaluation import runner, storage
from magail_sumo.expert import record_expert
from magail_sumo.sim.dynamics import BicycleLimits
from magail_sumo.training.config import TrainConfig
from magail_sumo.policies import CheckpointPolicy, load_checkpoint_policy
from magail_sumo.training.trainer import CheckpointError, load_policy, train

SID = "850c48d8bbfa008f"
SCENE = str(WOMD_DIR / f"{SID}.tfrecord")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory, bundled_networks):
    root = tmp_path_factory.mktemp("loader")
    nets = bundled_networks("850c48d8bbfa008f")
    record_expert(scene_specs([SCENE], nets), root / "expert")
    cfg = from_dict(TrainConfig, {
        "seed": 1, "expert_dir": str(root / "expert"), "out_dir": str(root / "runs"),
        "updates": 1, "env": {"max_steps": 20},
        "scenes": {"files": [SCENE], "networks": str(nets)},
        "policy": {"actor_hidden": [16, 16], "critic_hidden": [16, 16]},
        "ppo": {"n_steps": 8, "batch_size": 16, "n_epochs": 1},
        "discriminator": {"epochs": 2, "batch_size": 4, "transformer": {
            "embed_dim": 16, "num_layers": 1, "num_heads": 2, "ff_dim": 32}},
        "bc": {"epochs": 1, "batch_size": 64}})
    run = train(cfg, run_dir=root / "run", log=lambda s: None)
    return root, run / "checkpoints" / "latest.pt"


def _legacy_actions(policy, observations):
    """Evaluation's actions before sampling: tanh of the Gaussian mean, in the dict's order."""
    names = list(observations)
    x = np.stack([np.asarray(observations[n], np.float32).reshape(-1) for n in names])
    with torch.no_grad():
        a = policy._predict(torch.as_tensor(x), deterministic=True).numpy()
    return dict(zip(names, np.clip(a.astype(np.float32), -1.0, 1.0)))


class _LegacyPolicy:
    def __init__(self, policy) -> None:
        self.policy = policy

    def act(self, observations):
        return _legacy_actions(self.policy, observations)


def legacy_deterministic(seed: int) -> _LegacyPolicy:
    """``module:factory`` reference: the checkpoint in $MAGAIL_TEST_CHECKPOINT acting as
    evaluation did before it sampled."""
    return _LegacyPolicy(load_policy(os.environ["MAGAIL_TEST_CHECKPOINT"])[0])


@pytest.mark.sumo
def test_registered_loader_samples_seeded_actions(checkpoint):
    _, ckpt = checkpoint
    assert ".pt" in policies.POLICY_LOADERS
    pol = policies.make_policy(str(ckpt), seed=0)
    assert isinstance(pol, CheckpointPolicy) and not pol.deterministic
    rng = np.random.default_rng(0)
    obs = {str(k): rng.normal(size=pol.obs_dim).astype(np.float32) for k in range(5)}
    a = pol.act(obs)
    assert set(a) == set(obs) and pol.act({}) == {}
    assert all(a[k].shape == (2,) and a[k].dtype == np.float32 and np.all(np.abs(a[k]) <= 1)
               for k in obs)
    # the same seed reproduces the draws bit for bit, whatever order the agents come in
    again = policies.make_policy(str(ckpt), seed=0).act(dict(reversed(list(obs.items()))))
    assert all(np.array_equal(a[k], again[k]) for k in obs)
    # another seed, or the next step of the same generator, draws other actions
    other = policies.make_policy(str(ckpt), seed=9).act(obs)
    nxt = pol.act(obs)
    assert all(not np.array_equal(a[k], other[k]) and not np.array_equal(a[k], nxt[k])
               for k in obs)
    # samples scatter around the mean action: tanh of the Gaussian sample
    many = policies.make_policy(str(ckpt), seed=1)
    draws = np.stack([many.act({"0": obs["0"]})["0"] for _ in range(400)])
    policy, _ = load_policy(ckpt)
    with torch.no_grad():
        dist = policy.get_distribution(torch.as_tensor(obs["0"][None]))
    mu, sd = dist.distribution.mean[0].numpy(), dist.distribution.stddev[0].numpy()
    z = np.arctanh(np.clip(draws, -1 + 1e-6, 1 - 1e-6))
    assert np.allclose(z.mean(0), mu, atol=4 * sd.max() / 20) and np.allclose(z.std(0), sd,
                                                                              rtol=0.15)
    with pytest.raises(CheckpointError, match="observations have 3 values"):
        pol.act({"1": np.zeros(3, np.float32)})


@pytest.mark.sumo
def test_deterministic_loader_gives_the_mean_action(checkpoint):
    _, ckpt = checkpoint
    pol = policies.make_policy(str(ckpt), seed=0, deterministic=True)
    assert isinstance(pol, CheckpointPolicy) and pol.deterministic
    rng = np.random.default_rng(0)
    obs = {str(k): rng.normal(size=pol.obs_dim).astype(np.float32) for k in range(5)}
    a, b = pol.act(obs), policies.make_policy(str(ckpt), seed=9, deterministic=True).act(obs)
    want = _legacy_actions(load_policy(ckpt)[0], obs)
    assert all(np.array_equal(a[k], b[k]) and np.array_equal(a[k], want[k])
               and np.array_equal(a[k], pol.act(obs)[k]) for k in obs)
    assert load_checkpoint_policy(ckpt, seed=4, deterministic=True).deterministic


@pytest.mark.sumo
def test_other_env_refused(checkpoint):
    _, ckpt = checkpoint
    with pytest.raises(CheckpointError, match=r"env\.limits\.max_accel"):
        load_checkpoint_policy(ckpt, target=EnvConfig(limits=replace(BicycleLimits(),
                                                                      max_accel=3.0)))


def _rollouts(out, method):
    return storage.read_rollouts(out / "rollouts" / method / f"{SID}.parquet", load_scene(SCENE))


def _same(a, b) -> bool:
    return all(np.array_equal(getattr(a, n), getattr(b, n)) for n in ("x", "y", "heading"))


@pytest.mark.sumo
def test_evaluate_checkpoint_end_to_end(checkpoint, bundled_networks):
    root, ckpt = checkpoint
    out = root / "eval"
    rc = main(["evaluate", "--policy", str(ckpt), "--scenes", SCENE, "--rollouts", "2",
               "--baselines", "constvel", "--networks", str(bundled_networks(SID)),
               "--out", str(out)])
    assert rc == 0
    man = json.loads((out / "manifest.json").read_text())
    assert man["methods"] == ["run", "constvel"] and man["policy_spec"] == str(ckpt)
    assert man["deterministic"] is False
    df = pd.read_parquet(out / "rollouts" / "run" / f"{SID}.parquet")
    assert tuple(df.columns) == storage.COLUMNS and df["rollout"].nunique() == 2
    assert np.isfinite(df[["x", "y", "heading"]].to_numpy()).all()
    # sampled actions: the two rollouts (two rollout seeds) differ
    ro = _rollouts(out, "run")
    assert not np.array_equal(ro.x[0], ro.x[1]) and not np.array_equal(ro.y[0], ro.y[1])
    assert main(["report", str(out)]) == 0
    assert (out / "report" / "report.html").is_file()
    assert "policy under test: run (sampled actions)" in (out / "report" / "report.md").read_text()


@pytest.mark.sumo
def test_evaluate_seeded_sampling_and_deterministic(checkpoint, bundled_networks, monkeypatch):
    """The same seed reproduces sampled rollouts bit for bit (in other worker processes and
    batches); --deterministic rollouts are all alike and equal evaluation's earlier actions
    (tanh of the mean, the env's agent order)."""
    root, ckpt = checkpoint
    nets = bundled_networks(SID)
    first = root / "eval-sampled"
    assert main(["evaluate", "--policy", str(ckpt), "--scenes", SCENE, "--rollouts", "2",
                 "--baselines", "none", "--networks", str(nets), "--out", str(first),
                 "--seed", "5"]) == 0
    det = root / "eval-det"
    assert main(["evaluate", "--policy", str(ckpt), "--scenes", SCENE, "--rollouts", "2",
                 "--baselines", "none", "--networks", str(nets), "--out", str(det),
                 "--seed", "5", "--deterministic", "--name", "mean"]) == 0
    assert json.loads((det / "manifest.json").read_text())["deterministic"] is True
    sampled, mean = _rollouts(first, "run"), _rollouts(det, "mean")
    assert np.array_equal(mean.x[0], mean.x[1]) and np.array_equal(mean.y[0], mean.y[1])
    assert np.array_equal(mean.heading[0], mean.heading[1])
    assert not np.array_equal(sampled.x[0], mean.x[0])
    # the same seed again (rollouts were one per worker, now both in one): bit-identical
    monkeypatch.setenv("MAGAIL_TEST_CHECKPOINT", str(ckpt))
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    bundle = str(nets / SID)
    legacy = f"{__name__}:legacy_deterministic"
    batches = [runner.Batch(SCENE, SID, bundle, str(ckpt), (0, 1), 5),
               runner.Batch(SCENE, SID, bundle, legacy, (0,), 5)]
    got = {b.spec: ro for b, ro, err, _ in runner.run_batches(batches, 2) if err is None}
    assert len(got) == 2
    assert _same(got[str(ckpt)], sampled)
    old = got[legacy]
    assert all(np.array_equal(getattr(old, n)[0], getattr(mean, n)[0])
               for n in ("x", "y", "heading"))


@pytest.mark.sumo
def test_noise_scale_scales_the_sampled_noise(checkpoint, bundled_networks, tmp_path,
                                              monkeypatch):
    """``noise_scale`` k samples ``tanh(mu + k·sigma·eps)`` with the same draws: 0 gives the
    mean action, and the pre-tanh offset from the mean grows linearly in k; a pretrained card's
    ``sampling.noise_scale`` is the default, ``--noise-scale`` overrides it and the manifest
    records the one used; a policy without sampling noise, a negative or non-finite scale is
    refused."""
    from magail_sumo import pretrained
    from magail_sumo.agents import PolicyError

    _, ckpt = checkpoint
    rng = np.random.default_rng(3)
    pol = policies.make_policy(str(ckpt), seed=0)
    obs = {str(k): rng.normal(size=pol.obs_dim).astype(np.float32) for k in range(6)}
    mean = policies.make_policy(str(ckpt), seed=0, deterministic=True).act(obs)

    def offsets(k):
        a = policies.make_policy(str(ckpt), seed=4, noise_scale=k).act(obs)
        return np.stack([np.arctanh(a[n]) - np.arctanh(mean[n]) for n in obs])

    assert np.abs(offsets(0.0)).max() < 1e-5
    one, half = offsets(1.0), offsets(0.5)
    assert np.abs(one).max() > 0.05
    assert np.allclose(half, 0.5 * one, atol=1e-4)
    assert np.array_equal(policies.make_policy(str(ckpt), seed=4, noise_scale=1.0).act(obs)["0"],
                          policies.make_policy(str(ckpt), seed=4).act(obs)["0"])
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(PolicyError, match="noise scale must be a finite number >= 0"):
            policies.make_policy(str(ckpt), seed=0, noise_scale=bad)
    with pytest.raises(PolicyError, match="RandomPolicy has no sampling noise to scale"):
        policies.make_policy("random", seed=0, noise_scale=0.5)
    assert isinstance(policies.make_policy("random", seed=0, noise_scale=1.0), agents.RandomPolicy)

    # a pretrained card's sampling.noise_scale is the default; an explicit one overrides it
    reg = tmp_path / "registry"
    pretrained.export(ckpt, "calm", reg, noise_scale=0.25, noise_note="picked on train scenes")
    monkeypatch.setenv(pretrained.ENV_VAR, str(reg))
    assert policies.make_policy("pretrained:calm", seed=0).noise_scale == 0.25
    assert policies.make_policy("guarded:pretrained:calm", seed=0).noise_scale == 0.25
    assert policies.make_policy("pretrained:calm", seed=0, noise_scale=1.0).noise_scale == 1.0
    out = tmp_path / "eval"
    assert main(["evaluate", "--policy", "pretrained:calm", "--scenes", SCENE, "--rollouts",
                 "1", "--baselines", "none", "--networks", str(bundled_networks(SID)),
                 "--out", str(out), "--noise-scale", "0.5"]) == 0
    assert json.loads((out / "manifest.json").read_text())["noise_scale"] == 0.5
    assert main(["report", str(out)]) == 0
    assert "policy under test: calm (sampled actions, noise scale 0.5)" in \
        (out / "report" / "report.md").read_text()
