"""GameFormer: network (shapes, masking, equivariance, level-k masking), loss, samples from
real scenes, training with exact resume, open-loop metrics and the closed-loop sim agent."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest import WOMD_DIR
from converters import load_scene
from magail_sumo.config import ConfigError, from_dict
from magail_sumo.models.gameformer import (AGENT_FEATURES, MAP_FEATURES, GameFormer,
                                           GameFormerModelConfig, gmm_nll, interaction_term,
                                           level_loss)
from magail_sumo.training.config import TrainConfig

SCENE = str(WOMD_DIR / "850c48d8bbfa008f.tfrecord")
TINY = {"d_model": 16, "num_heads": 2, "fusion_layers": 1, "ff_dim": 32, "modes": 3,
        "levels": 2, "future_steps": 12}


def _model(seed: int = 0) -> GameFormer:
    torch.manual_seed(seed)
    return GameFormer(GameFormerModelConfig(**TINY)).eval()


def _inputs(b=2, n=4, th=11, nm=5, p=4, seed=1):
    g = torch.Generator().manual_seed(seed)
    agents = torch.randn(b, n, th, AGENT_FEATURES, generator=g) * 3
    agent_mask = torch.ones(b, n, dtype=torch.bool)
    agent_mask[:, -1] = False
    mp = torch.randn(b, n, nm, p, MAP_FEATURES, generator=g) * 3
    mm = torch.ones(b, n, nm, p, dtype=torch.bool)
    mm[:, :, -1] = False  # a padded element
    mm[:, :, 0, -1] = False  # a padded point
    return agents, agent_mask, mp, mm


def test_output_shapes():
    model = _model()
    outs = model(*_inputs())
    assert len(outs) == TINY["levels"] + 1
    for traj, scores in outs:
        assert traj.shape == (2, 4, 3, 12, 4) and scores.shape == (2, 4, 3)
        assert torch.isfinite(traj).all() and torch.isfinite(scores).all()
        ls = traj[..., 2:]
        assert ls.min() >= -1.6 - 1e-6 and ls.max() <= 3.0 + 1e-6


def test_padding_does_not_change_valid_agents():
    model = _model()
    agents, am, mp, mm = _inputs()
    ref = model(agents, am, mp, mm)
    a2, m2 = agents.clone(), mp.clone()
    a2[:, -1] = 100.0  # the padded agent
    m2[:, :, -1] = -50.0  # padded map elements
    m2[:, :, 0, -1] = 77.0  # a padded point
    got = model(a2, am, m2, mm)
    for (t0, s0), (t1, s1) in zip(ref, got):
        torch.testing.assert_close(t1[:, :-1], t0[:, :-1], rtol=1e-5, atol=1e-4)
        torch.testing.assert_close(s1[:, :-1], s0[:, :-1], rtol=1e-5, atol=1e-4)


def test_permutation_equivariance_over_agents():
    model = _model()
    agents, am, mp, mm = _inputs()
    am[:] = True
    perm = torch.tensor([2, 0, 3, 1])
    ref = model(agents, am, mp, mm)
    got = model(agents[:, perm], am[:, perm], mp[:, perm], mm[:, perm])
    for (t0, s0), (t1, s1) in zip(ref, got):
        torch.testing.assert_close(t1, t0[:, perm], rtol=1e-4, atol=1e-4)
        torch.testing.assert_close(s1, s0[:, perm], rtol=1e-4, atol=1e-4)


def test_gmm_nll_by_hand():
    # one agent, two steps: mu (0, 0), (1, 1); log sigma (0, ln 2), (ln 0.5, 0); truth (1, 2), (1, 1)
    traj = torch.tensor([[[[0.0, 0.0, 0.0, math.log(2.0)], [1.0, 1.0, math.log(0.5), 0.0]]]])
    fut = torch.tensor([[[[1.0, 2.0], [1.0, 1.0]]]])
    step1 = 0.0 + math.log(2.0) + 0.5 * (1.0 ** 2 + (2.0 / 2.0) ** 2)
    step2 = math.log(0.5) + 0.0 + 0.5 * (0.0 + 0.0)
    got = gmm_nll(traj[:, :], fut[:, :, :], torch.ones(1, 1, 2, dtype=torch.bool))
    assert got.item() == pytest.approx((step1 + step2) / 2, abs=1e-6)
    only_first = gmm_nll(traj, fut, torch.tensor([[[True, False]]]))
    assert only_first.item() == pytest.approx(step1, abs=1e-6)
    # level loss: the best mode is the one nearer the truth; CE against it
    modes = torch.stack([traj[0, 0] + 10.0 * torch.tensor([1.0, 1.0, 0, 0]), traj[0, 0]])
    modes = modes[None, None]  # (1, 1, 2, T, 4)
    scores = torch.tensor([[[0.5, -0.5]]])
    lv = level_loss(modes, scores, fut, torch.ones(1, 1, 2, dtype=torch.bool),
                    torch.ones(1, 1, dtype=torch.bool))
    assert lv.nll.item() == pytest.approx((step1 + step2) / 2, abs=1e-6)
    ce = -math.log(math.exp(-0.5) / (math.exp(0.5) + math.exp(-0.5)))
    assert lv.score.item() == pytest.approx(ce, abs=1e-6)
    assert lv.total.item() == pytest.approx(lv.nll.item() + ce, abs=1e-6)


def test_interaction_term_by_hand():
    # two agents, one mode, 5 steps: scored at the last step only (stride 5); 1 m apart there
    a = torch.zeros(1, 2, 1, 5, 2)
    a[0, 1, 0, :, 0] = 10.0
    a[0, 1, 0, 4, 0] = 1.0
    mask = torch.ones(1, 2, dtype=torch.bool)
    got = interaction_term(a, a, mask, 3.0)
    assert got[0].tolist() == pytest.approx([0.5, 0.5])
    assert interaction_term(a, a, mask, 0.5)[0].tolist() == [0.0, 0.0]  # beyond the distance
    assert interaction_term(a, a, torch.tensor([[True, False]]), 3.0)[0, 0].item() == 0.0


def test_level_k_masks_own_previous_future():
    model = _model()
    agents, am, mp, mm = _inputs(b=1)
    am[:] = True
    with torch.no_grad():
        ctx, pad = model.encode(agents, am, mp, mm)
        traj, scores, z = model.decode_level0(ctx, pad)
        dec = model.levels[0]
        a_mf, tokens = dec.future_tokens(traj, scores, am)
        ref = dec.decode(tokens, a_mf, z, ctx, pad, am)
        i = 1
        t2 = tokens.clone()
        t2[:, i] += 5.0  # agent i's level-0 future token
        got = dec.decode(t2, a_mf, z, ctx, pad, am)
    for r, g in zip(ref, got):
        torch.testing.assert_close(g[:, i], r[:, i])  # i never attends its own future
        others = [k for k in range(4) if k != i]
        assert not torch.allclose(g[:, others], r[:, others])  # the others do


def _cfg(tmp_path, **over) -> TrainConfig:
    d = {"algorithm": "gameformer", "seed": 5, "out_dir": str(tmp_path / "runs"),
         "updates": 4, "checkpoint_every": 2, "scenes": {"files": [SCENE]},
         "gameformer": {"model": dict(TINY, future_steps=80), "max_agents": 4,
                        "map_elements": 4, "map_points": 5, "batch_size": 4,
                        "window_stride": 20, "eval_stride": 40}}
    d.update(over)
    return from_dict(TrainConfig, d)


def test_config_checks():
    with pytest.raises(ConfigError, match="num_heads"):
        from_dict(TrainConfig, {"algorithm": "gameformer",
                                "gameformer": {"model": {"d_model": 10, "num_heads": 3}}})
    with pytest.raises(ConfigError, match="focal_types"):
        from_dict(TrainConfig, {"gameformer": {"focal_types": ["bus"]}})
    with pytest.raises(ConfigError, match="min_future_steps"):
        from_dict(TrainConfig, {"gameformer": {"min_future_steps": 81}})


def test_samples_index_the_log(tmp_path):
    from magail_sumo.training.gameformer.data import (Frame, StreamingDataset, scene_data,
                                                      training_sample)
    from converters.scene_files import list_records

    cfg = _cfg(tmp_path)
    g = cfg.gameformer
    scene = load_scene(SCENE)
    tr = scene.tracks
    c = 40
    row = int(np.flatnonzero(tr.valid[:, c] & (tr.type == 1))[0])
    s = training_sample(scene_data(scene, g), c, row, g)
    assert s["rows"][0] == row and s["agent_mask"][0]
    fr = Frame(*s["frame"])
    assert (fr.x, fr.y, fr.heading) == (tr.x[row, c], tr.y[row, c],
                                        pytest.approx(tr.heading[row, c]))
    hx, hy = fr.to_world(s["agents"][0, :, 0].astype(np.float64),
                         s["agents"][0, :, 1].astype(np.float64))
    steps = np.arange(c - 10, c + 1)
    ok = tr.valid[row, steps]
    np.testing.assert_allclose(hx[ok], tr.x[row, steps][ok], atol=1e-3)
    np.testing.assert_allclose(hy[ok], tr.y[row, steps][ok], atol=1e-3)
    assert (s["agents"][0, ~ok] == 0).all() and (s["agents"][0, ok, 8] == 1).all()
    fut = np.arange(c + 1, c + 81)
    inside = fut < scene.num_steps  # a 91-step scene: the future is cut at step 90
    mask = np.zeros(80, bool)
    mask[inside] = tr.valid[row, fut[inside]]
    np.testing.assert_array_equal(s["future_mask"][0], mask)
    fx, fy = fr.to_world(s["future"][0, :, 0].astype(np.float64),
                         s["future"][0, :, 1].astype(np.float64))
    np.testing.assert_allclose(fx[mask], tr.x[row, fut[mask]], atol=1e-3)
    np.testing.assert_allclose(fy[mask], tr.y[row, fut[mask]], atol=1e-3)
    # other agents: the nearest observed ones, nearest first
    others = s["rows"][1:][s["rows"][1:] >= 0]
    d = np.hypot(tr.x[others, c] - tr.x[row, c], tr.y[others, c] - tr.y[row, c])
    assert (np.diff(d) >= 0).all() and tr.valid[others, c].all()
    # the stream: one epoch serves every sample once; batches are a function of (seed, position)
    refs = list_records(SCENE)
    ds, ds2 = StreamingDataset(refs, g, 5), StreamingDataset(refs, g, 5)
    order = ds.epoch_order(0)
    assert len(order) == ds.num_samples and len({tuple(r) for r in order}) == ds.num_samples
    assert not np.array_equal(order, ds.epoch_order(1))
    b1, b2 = ds.batch(3), ds2.batch(3)
    assert all(torch.equal(b1[k], b2[k]) for k in b1)


def test_train_and_exact_resume(tmp_path):
    from magail_sumo.training.trainer import load_checkpoint, train

    cfg = _cfg(tmp_path)
    straight = train(cfg, run_dir=tmp_path / "a", log=lambda m: None)
    half = train(_cfg(tmp_path, updates=2), run_dir=tmp_path / "b", log=lambda m: None)
    resumed = train(cfg, resume=half, log=lambda m: None)
    a = load_checkpoint(straight / "checkpoints" / "latest.pt")
    b = load_checkpoint(resumed / "checkpoints" / "latest.pt")
    assert a["update"] == b["update"] == 4
    assert a["config"]["algorithm"] == "gameformer"
    assert a["policy"].keys() == b["policy"].keys()
    for k in a["policy"]:
        assert torch.equal(a["policy"][k], b["policy"][k]), k
    assert (straight / "checkpoints" / "update_000002.pt").is_file()


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from magail_sumo.training.trainer import train

    tmp = tmp_path_factory.mktemp("gf")
    run = train(_cfg(tmp, updates=2), run_dir=tmp / "run", log=lambda m: None)
    return run / "checkpoints" / "latest.pt"


def test_openloop_metrics(trained, tmp_path):
    from magail_sumo.evaluation.openloop import misses, speed_scale

    assert speed_scale(np.array([0.0, 1.4, 6.2, 11.0, 30.0])).tolist() == \
        pytest.approx([0.5, 0.5, 0.75, 1.0, 1.0])
    gt = np.zeros((1, 80, 2))
    head = np.zeros((1, 80))
    pred = np.zeros((1, 2, 80, 2))
    pred[0, 0, :, 0] = 1.9  # 1.9 m ahead: inside the 3-s longitudinal 2 m at full speed
    pred[0, 1, :, 1] = 1.5  # 1.5 m aside: outside 1.0 lateral at 3 s, inside 1.8 at 5 s
    got = misses(pred[:, 1:], gt, head, np.ones((1, 80), bool), np.array([20.0]))
    assert got.tolist() == [[1.0, 0.0, 0.0]]
    got = misses(pred[:, :1], gt, head, np.ones((1, 80), bool), np.array([0.0]))
    assert got.tolist() == [[1.0, 1.0, 0.0]]  # scaled by 0.5 at standstill: 1.9 > 1.0, 1.8
    valid = np.ones((1, 80), bool)
    valid[0, 49] = False
    assert np.isnan(misses(pred, gt, head, valid, np.array([20.0]))[0, 1])

    import importlib.util

    path = WOMD_DIR.parents[1] / "benchmarks" / "gameformer_openloop.py"
    spec = importlib.util.spec_from_file_location("gameformer_openloop", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)

    assert bench.main([str(trained), "--scenes", SCENE]) == 1  # trained on it: refused
    assert bench.main([str(trained), "--scenes", SCENE, "--allow-trained-scenes",
                       "--max-windows", "1"]) == 0


@pytest.mark.sumo
def test_closed_loop_evaluate(trained, tmp_path, bundled_networks):
    import pandas as pd

    from magail_sumo.cli.main import main
    from magail_sumo.policies import make_policy
    from magail_sumo.policies import GameFormerPolicy

    assert isinstance(make_policy(str(trained), 3), GameFormerPolicy)
    out = tmp_path / "eval"
    rc = main(["evaluate", "--policy", str(trained), "--scenes", SCENE, "--rollouts", "2",
               "--out", str(out), "--baselines", "none", "--workers", "1", "--name", "gf",
               "--networks", str(bundled_networks("850c48d8bbfa008f"))])
    assert rc == 0
    df = pd.read_parquet(next((out / "rollouts" / "gf").glob("*.parquet")))
    assert sorted(df["rollout"].unique()) == [0, 1]
    assert np.isfinite(df[["x", "y", "heading"]].to_numpy()).all()


def test_pt_loader_dispatches_on_the_algorithm(trained):
    from magail_sumo.policies import GameFormerPolicy
    from magail_sumo.policies import load_checkpoint_policy

    pol = load_checkpoint_policy(trained, seed=4, deterministic=True)
    assert isinstance(pol, GameFormerPolicy) and pol.deterministic
    with pytest.raises(RuntimeError, match="begin"):
        pol.act({"1": np.zeros(3, np.float32)})
