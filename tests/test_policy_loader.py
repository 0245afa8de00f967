"""Training checkpoints as `magail-sumo evaluate --policy RUN/checkpoints/latest.pt` policies."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from conftest import WOMD_DIR
from magail_sumo.cli.main import main
from magail_sumo.config import from_dict
from magail_sumo.env.config import EnvConfig
from magail_sumo.env.vec_env import scene_specs
from magail_sumo.evaluation import rollouts as rl
from magail_sumo.expert import record_expert
from magail_sumo.sim.dynamics import BicycleLimits
from magail_sumo.training.config import TrainConfig
from magail_sumo.training.policy_loader import CheckpointPolicy, load_checkpoint_policy
from magail_sumo.training.trainer import CheckpointError, train

SID = "850c48d8bbfa008f"
SCENE = str(WOMD_DIR / f"{SID}.tfrecord")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    root = tmp_path_factory.mktemp("loader")
    nets = root / "nets"
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


@pytest.mark.sumo
def test_registered_loader_gives_deterministic_actions(checkpoint):
    _, ckpt = checkpoint
    assert ".pt" in rl.POLICY_LOADERS
    pol = rl.make_policy(str(ckpt), seed=0)
    assert isinstance(pol, CheckpointPolicy)
    rng = np.random.default_rng(0)
    obs = {str(k): rng.normal(size=pol.obs_dim).astype(np.float32) for k in range(5)}
    a, b = pol.act(obs), rl.make_policy(str(ckpt), seed=9).act(obs)
    assert set(a) == set(obs) and pol.act({}) == {}
    for k in obs:
        assert a[k].shape == (2,) and np.all(np.abs(a[k]) <= 1) and np.array_equal(a[k], b[k])
    with pytest.raises(CheckpointError, match="observations have 3 values"):
        pol.act({"1": np.zeros(3, np.float32)})


@pytest.mark.sumo
def test_other_env_refused(checkpoint):
    _, ckpt = checkpoint
    with pytest.raises(CheckpointError, match=r"env\.limits\.max_accel"):
        load_checkpoint_policy(ckpt, target=EnvConfig(limits=replace(BicycleLimits(),
                                                                      max_accel=3.0)))


@pytest.mark.sumo
def test_evaluate_checkpoint_end_to_end(checkpoint):
    root, ckpt = checkpoint
    out = root / "eval"
    rc = main(["evaluate", "--policy", str(ckpt), "--scenes", SCENE, "--rollouts", "2",
               "--baselines", "constvel", "--networks", str(root / "nets"), "--out", str(out)])
    assert rc == 0
    man = json.loads((out / "manifest.json").read_text())
    assert man["methods"] == ["run", "constvel"] and man["policy_spec"] == str(ckpt)
    df = pd.read_parquet(out / "rollouts" / "run" / f"{SID}.parquet")
    assert tuple(df.columns) == rl.COLUMNS and df["rollout"].nunique() == 2
    assert np.isfinite(df[["x", "y", "heading"]].to_numpy()).all()
    assert main(["report", str(out)]) == 0
    assert (out / "report" / "report.html").is_file()
