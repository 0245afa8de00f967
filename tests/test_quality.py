"""Pretrained policies (``--policy pretrained[:NAME]``) and the quality benchmark
(benchmarks/quality.py) end to end, with a checkpoint of a 1-update training run."""

from __future__ import annotations

import fnmatch
import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from conftest import ROOT, WOMD_DIR
from magail_sumo import pretrained as pt
from magail_sumo.cli.main import main
from magail_sumo.config import from_dict
from magail_sumo.env.scene_specs import scene_specs
from magail_sumo import policies
from magail_sumo.evaluation import storage
from magail_sumo.evaluation.realism.config import BUCKETS, CHALLENGE_2025
from magail_sumo.expert import record_expert
from magail_sumo.training.config import TrainConfig
from magail_sumo.training.trainer import train

SID = "850c48d8bbfa008f"  # a training scene of configs/splits/womd14.yaml
SCENE = str(WOMD_DIR / f"{SID}.tfrecord")
SPLIT = ROOT / "configs" / "splits" / "womd14.yaml"
HELD_OUT = ROOT / "data" / "scenarionet" / "8799c31b5be1f312.pkl"  # a test scene


# ------------------------------------------------------------------ registry without SUMO
def test_registry_errors_name_the_spec_and_the_available(tmp_path, monkeypatch):
    monkeypatch.delenv(pt.ENV_VAR, raising=False)
    assert pt.available(tmp_path / "absent") == [] and pt.default_name(tmp_path) is None
    with pytest.raises(pt.PretrainedError, match=r"^pretrained: no default pretrained policy "
                                                 r"\(index.json names none.*available: none"):
        pt.resolve("pretrained", tmp_path)
    (tmp_path / "a.pt").write_bytes(b"x")
    (tmp_path / "a.json").write_text("{}")
    (tmp_path / "b.pt").write_bytes(b"x")  # no card: not available
    assert pt.available(tmp_path) == ["a"]
    with pytest.raises(pt.PretrainedError, match=r"pretrained:nope: unknown pretrained policy "
                                                 r"'nope' \(available: a; folder "):
        pt.resolve("pretrained:nope", tmp_path)
    with pytest.raises(pt.PretrainedError, match=r"b.json: card missing beside b.pt"):
        pt.resolve("pretrained:b", tmp_path)
    for bad in ("../a", "sumo", ".a", ""):
        with pytest.raises(pt.PretrainedError, match="is not a pretrained policy name"):
            pt.resolve(f"pretrained:{bad}", tmp_path)
    (tmp_path / "index.json").write_text('["a"]')
    with pytest.raises(pt.PretrainedError, match="index must be a JSON object"):
        pt.resolve("pretrained", tmp_path)
    (tmp_path / "index.json").write_text('{"default": "a"}')
    assert pt.resolve("pretrained", tmp_path).name == "a"
    # the environment variable selects the folder; evaluate's spec errors are one line
    monkeypatch.setenv(pt.ENV_VAR, str(tmp_path))
    assert pt.registry_dir() == tmp_path and policies.method_name("pretrained") == "a"
    assert policies.method_name("pretrained:zz") == "zz"
    with pytest.raises(pt.PretrainedError, match="unknown pretrained policy 'zz'"):
        policies.make_policy("pretrained:zz", 0)


@pytest.fixture
def pretrained_cli(capsys):
    """``python -m magail_sumo.pretrained ARGS`` (its ``main``, in this process): exit status,
    stderr lines."""
    from magail_sumo.pretrained.__main__ import main as pretrained_main

    def run(*args: str) -> tuple[int, list[str]]:
        capsys.readouterr()
        rc = pretrained_main(list(args))
        return rc, capsys.readouterr().err.strip().splitlines()

    return run


def test_export_checks_everything_before_replacing_a_registered_policy(tmp_path,
                                                                      pretrained_cli):
    """Exporting again under a registered name with a bad --noise-scale (or a bad figures
    file) is refused before NAME.pt is touched: the registered policy still resolves, its
    card's checksum matching."""
    from conftest import tiny_checkpoint

    first, second = tiny_checkpoint(tmp_path / "a.pt", {}), tmp_path / "b.pt"
    torch.manual_seed(7)
    tiny_checkpoint(second, {"max_steps": 30})  # another policy: other weights
    reg = tmp_path / "reg"
    pt.export(first, "mine", reg, make_default=True)
    before = {f: (reg / f).read_bytes() for f in sorted(os.listdir(reg))}
    (tmp_path / "deep.json").write_text("[" * 100000)
    for bad in (["--noise-scale", "-1"], ["--noise-scale", "nan"],
                ["--figures", str(tmp_path / "deep.json")]):
        rc, err = pretrained_cli("export", str(second), "--name", "mine", "--dir", str(reg),
                                 "--default", *bad)
        assert rc == 1 and len(err) == 1 and err[0].startswith("error: "), err
        assert {f: (reg / f).read_bytes() for f in sorted(os.listdir(reg))} == before, bad
    assert pt.resolve("pretrained:mine", reg).card["checkpoint"]["source"] == str(first)
    # a good export replaces the three files together (no temporary left)
    pt.export(second, "mine", reg, noise_scale=0.5, make_default=True)
    assert sorted(os.listdir(reg)) == ["index.json", "mine.json", "mine.pt"]
    entry = pt.resolve("pretrained:mine", reg)
    assert entry.card["checkpoint"]["source"] == str(second)
    assert entry.card["sampling"]["noise_scale"] == 0.5


def test_pretrained_cli_errors_are_one_line_naming_the_file(tmp_path, pretrained_cli):
    """``python -m magail_sumo.pretrained``: every error one line naming the file the user gave
    (no traceback; --debug prints it)."""
    from conftest import tiny_checkpoint

    ckpt = tiny_checkpoint(tmp_path / "c.pt", {})
    (tmp_path / "deep.json").write_text("[" * 100000)
    (tmp_path / "afile").write_text("x")
    reg, deep = str(tmp_path / "reg"), tmp_path / "deep.json"
    import os

    os.mkfifo(tmp_path / "fifo.json")  # would block open() forever
    cases = [
        (["export", str(ckpt), "--name", "a", "--dir", reg, "--figures",
          str(tmp_path / "fifo.json")], "fifo.json: cannot read the figures file (is a FIFO"),
        (["export", str(ckpt), "--name", "a", "--dir", reg, "--figures", str(deep)],
         f"{deep}: figures file is nested too deep"),
        (["export", str(ckpt), "--name", "a", "--dir", reg, "--figures", str(tmp_path)],
         f"{tmp_path}: cannot read the figures file"),
        (["export", str(tmp_path), "--name", "a", "--dir", reg], f"{tmp_path}: "),
        (["export", str(ckpt), "--name", "a", "--dir", str(tmp_path / "afile")],
         f"{tmp_path / 'afile'}: not a folder"),
        (["export", str(ckpt), "--name", "../a", "--dir", reg], "not a pretrained policy name"),
        (["list", "--dir", str(tmp_path / "afile" / "x")], None),
    ]
    (tmp_path / "bad_index").mkdir()
    (tmp_path / "bad_index" / "index.json").write_text("[" * 100000)
    cases.append((["list", "--dir", str(tmp_path / "bad_index")],
                  f"{tmp_path / 'bad_index' / 'index.json'}: index is nested too deep"))
    for args, want in cases:
        rc, err = pretrained_cli(*args)
        if want is None:
            assert rc == 0, err
            continue
        assert rc == 1 and len(err) == 1, (args, err)
        assert err[0].startswith("error: ") and want in err[0], (args, err)
    rc, err = pretrained_cli("--debug", *cases[0][0])
    assert rc == 1 and err[0].startswith("Traceback") and err[-1].startswith("error: ")
    assert not (tmp_path / "reg").exists() or os.listdir(tmp_path / "reg") == []


def test_shipped_registry_and_package_data():
    folder = Path(pt.__file__).parent
    default = pt.default_name(folder)
    assert default is not None and default in pt.available(folder)
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    patterns = data["tool"]["setuptools"]["package-data"]["magail_sumo.pretrained"]
    for name in ("x.pt", "x.json", "index.json", "README.md"):
        assert any(fnmatch.fnmatch(name, p) for p in patterns), name
    assert (folder / "__init__.py").is_file()  # a package: setuptools' find includes it


def test_shipped_default_policy_loads_and_acts(monkeypatch):
    """`--policy pretrained` from a plain install: the shipped default's card matches its
    checkpoint, it was trained on the split's train scenes only, and it acts (sampled and
    seeded, or deterministic) on observations of the evaluation layout."""
    from magail_sumo.env.config import EnvConfig
    from magail_sumo.splits import load_split, scene_stem
    from magail_sumo.sensors.observation import observation_bounds

    monkeypatch.delenv(pt.ENV_VAR, raising=False)
    entry = pt.resolve("pretrained")
    card = json.loads(entry.checkpoint.with_suffix(".json").read_text())
    assert card["checkpoint"]["sha256"] == pt.sha256(entry.checkpoint)
    trained = {scene_stem(f) for f in card["config"]["scenes"]["files"]}
    split = load_split(ROOT / card["split"]["file"])  # the split it was trained under
    assert trained and trained <= {scene_stem(f) for f in split.train}
    assert not trained & {scene_stem(f) for f in split.test}
    # the evaluation layout with the policy's optional features (the default: the leader
    # sensor), and the gap guard it was trained behind
    policy = policies.make_policy("pretrained", 7)
    low, high = observation_bounds(getattr(policy, "observation", EnvConfig().observation))
    assert low.shape == (policy.obs_dim,)
    assert getattr(policy, "guard", None) is None or policy.guard.on
    # it samples with the noise scale its card gives (chosen on train scenes), else 1
    assert policy.noise_scale == (card.get("sampling") or {}).get("noise_scale", 1.0)
    obs = {str(k): np.clip(np.zeros_like(low), low, high) for k in range(5)}
    a1 = policy.act(obs)
    a2 = policies.make_policy("pretrained", 7).act(dict(reversed(list(obs.items()))))
    for k in obs:
        assert a1[k].shape == (2,) and np.all(np.abs(a1[k]) <= 1.0)
        np.testing.assert_array_equal(a1[k], a2[k])
    d = policies.make_policy("pretrained", 7, deterministic=True).act(obs)
    # same observation, same mean action (to the last bits: torch's tanh rounds the rows of a
    # vector block and the scalar tail after it differently)
    assert all(np.allclose(d["0"], d[k], rtol=0, atol=1e-6) for k in obs)


# --------------------------------------------------------------- with a trained checkpoint
@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory, bundled_networks):
    root = tmp_path_factory.mktemp("pretrained")
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


@pytest.fixture(scope="module")
def registry(checkpoint):
    root, ckpt = checkpoint
    reg = root / "registry"
    entry = pt.export(ckpt, "tiny", reg, description="1-update test run", split=SPLIT,
                      figures={"note": "none"}, make_default=True)
    return reg, entry


@pytest.mark.sumo
def test_export_writes_a_slim_checkpoint_and_its_card(checkpoint, registry, tmp_path,
                                                     monkeypatch):
    _, ckpt = checkpoint
    reg, entry = registry
    assert entry.name == "tiny" and entry.checkpoint == reg / "tiny.pt"
    assert pt.available(reg) == ["tiny"] and pt.default_name(reg) == "tiny"
    state = torch.load(entry.checkpoint, weights_only=True)
    assert sorted(state) == ["config", "format", "policy", "update"]
    card = json.loads((reg / "tiny.json").read_text())
    assert card["checkpoint"]["sha256"] == pt.sha256(entry.checkpoint)
    assert card["config"]["scenes"]["files"] == [SCENE] and card["figures"] == {"note": "none"}
    assert card["split"]["test"][-1] == "data/scenarionet/8799c31b5be1f312.pkl"
    # the same policy as the run's checkpoint
    monkeypatch.setenv(pt.ENV_VAR, str(reg))
    a, b = policies.make_policy("pretrained", 0), policies.make_policy(str(ckpt), 0)
    obs = {str(k): np.random.default_rng(k).normal(size=a.obs_dim).astype(np.float32)
           for k in range(4)}
    got, want = a.act(obs), b.act(obs)
    assert all(np.array_equal(got[k], want[k]) for k in obs)
    # a replaced checkpoint is refused
    copy = tmp_path / "reg"
    copy.mkdir()
    for f in ("tiny.pt", "tiny.json"):
        (copy / f).write_bytes((reg / f).read_bytes())
    with open(copy / "tiny.pt", "ab") as fh:
        fh.write(b"\0")
    with pytest.raises(pt.PretrainedError, match="sha256 differs from its card's"):
        pt.resolve("pretrained:tiny", copy)
    # a run trained on a split's test scene is refused
    split = tmp_path / "split.yaml"
    split.write_text(f"train: [data/womd/637f20cafde22ff8.tfrecord]\ntest: [{SCENE}]\n")
    with pytest.raises(pt.PretrainedError, match=f"trained on {SCENE}, a test scene"):
        pt.export(ckpt, "other", tmp_path / "reg2", split=split)
    assert not (tmp_path / "reg2" / "other.pt").exists()


@pytest.mark.sumo
def test_evaluate_pretrained_end_to_end(checkpoint, registry, bundled_networks, monkeypatch,
                                       capsys):
    root, _ = checkpoint
    reg, _ = registry
    monkeypatch.setenv(pt.ENV_VAR, str(reg))
    out = root / "eval"
    rc = main(["evaluate", "--policy", "pretrained:tiny", "--scenes", SCENE, "--rollouts", "2",
               "--baselines", "constvel", "--networks", str(bundled_networks(SID)),
               "--out", str(out)])
    assert rc == 0
    man = json.loads((out / "manifest.json").read_text())
    assert man["methods"] == ["tiny", "constvel"] and man["policy_spec"] == "pretrained:tiny"
    df = pd.read_parquet(out / "rollouts" / "tiny" / f"{SID}.parquet")
    assert tuple(df.columns) == storage.COLUMNS and df["rollout"].nunique() == 2
    assert np.isfinite(df[["x", "y", "heading"]].to_numpy()).all()
    capsys.readouterr()
    rc = main(["evaluate", "--policy", "pretrained:nope", "--scenes", SCENE, "--rollouts", "2",
               "--out", str(root / "eval2")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and err == [f"error: magail-sumo evaluate: pretrained:nope: unknown "
                               f"pretrained policy 'nope' (available: tiny; folder {reg})"]


def _benchmark(args: list[str], reg: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env[pt.ENV_VAR] = str(reg)
    return subprocess.run([sys.executable, str(ROOT / "benchmarks" / "quality.py"), *args],
                          env=env, capture_output=True, text=True, timeout=900)


@pytest.mark.sumo
def test_quality_benchmark_end_to_end(checkpoint, registry, tmp_path):
    reg, _ = registry
    out = tmp_path / "q"
    res = _benchmark(["--policy", "tiny=pretrained:tiny", "--baselines", "constvel",
                      "logreplay", "--scenes", str(HELD_OUT), "--seeds", "0", "--rollouts", "2",
                      "--workers", "2", "--out", str(out), "--json"], reg)
    assert res.returncode == 0, res.stderr[-3000:]
    got = json.loads(res.stdout)
    assert got["methods"] == {"constvel": "constvel", "logreplay": "logreplay",
                              "tiny": "pretrained:tiny"}
    (scene,) = got["scenes"]
    assert scene["scenario_id"] == "8799c31b5be1f312-w0" and scene["split"] == "test"
    assert scene["source_file"] == "data/scenarionet/8799c31b5be1f312.pkl"
    assert scene["scored_agents"] > 1  # the window has tracks to predict besides the SDC
    assert got["scored"] == {m: ["8799c31b5be1f312-w0"] for m in got["methods"]}
    rows = {(r["method"], r["metric"]): r for r in got["rows"]}
    fields = ["realism_meta_metric", "kinematic_metrics", "interactive_metrics",
              "map_based_metrics", "min_ade", "simulated_collision_rate",
              "simulated_offroad_rate", "simulated_traffic_light_violation_rate", "speed_bias"]
    assert sorted(rows) == sorted((m, f) for m in got["methods"] for f in fields)
    for r in got["rows"]:
        assert r["seeds"] == [0] and r["mean"] == r["min"] == r["max"] == r["per_seed"][0]
    # the values are the report's (evaluate + report ran once per seed into OUT/seed0)
    metrics = pd.read_csv(out / "seed0" / "report" / "metrics.csv").set_index("method")
    for m in got["methods"]:
        assert rows[(m, "realism_meta_metric")]["mean"] == pytest.approx(
            metrics.loc[m, "metametric"], abs=1e-12)
        assert rows[(m, "speed_bias")]["mean"] == pytest.approx(metrics.loc[m, "speed_bias"],
                                                                abs=1e-12)
        assert rows[(m, "min_ade")]["mean"] == pytest.approx(
            metrics.loc[m, "min_average_displacement_error"], abs=1e-12)
        # the meta-metric is the weighted sum of its three components
        total = sum(rows[(m, b)]["mean"] * sum(CHALLENGE_2025.feature(n).weight for n in ns)
                    for b, ns in BUCKETS.items())
        assert total == pytest.approx(rows[(m, "realism_meta_metric")]["mean"], abs=1e-9)
    assert rows[("logreplay", "min_ade")]["mean"] == 0.0
    assert rows[("logreplay", "speed_bias")]["mean"] == pytest.approx(0.0, abs=1e-6)
    assert rows[("logreplay", "realism_meta_metric")]["mean"] > \
        rows[("constvel", "realism_meta_metric")]["mean"]
    man = json.loads((out / "seed0" / "manifest.json").read_text())
    assert man["methods"] == ["constvel", "logreplay", "tiny"]  # baselines once, then the policy
    # bootstrap intervals: one scene, one seed -> the interval is the point itself
    assert got["seed_groups"] == {} and list(got["intervals"]) == list(got["methods"])
    for m, rec in got["intervals"].items():
        mm = rec["figures"]["realism_meta_metric"]
        assert rec["members"] == [m]
        assert mm["mean"] == pytest.approx(rows[(m, "realism_meta_metric")]["mean"], abs=1e-12)
        assert mm["lo"] == pytest.approx(mm["mean"]) and mm["hi"] == pytest.approx(mm["mean"])
    pairs = {(c["a"], c["b"]): c for c in got["comparisons"]}
    assert sorted(pairs) == [("constvel", "logreplay"), ("constvel", "tiny"),
                             ("logreplay", "tiny")]
    c = pairs[("constvel", "logreplay")]
    assert c["difference"]["mean"] == pytest.approx(
        rows[("constvel", "realism_meta_metric")]["mean"]
        - rows[("logreplay", "realism_meta_metric")]["mean"], abs=1e-12)
    assert c["verdict"] == "logreplay better than constvel"
    # --merge: runs made apart (here: a copy of the policy's rows under another name, as a
    # second training seed would be) combined, the two as one seed group, no rollouts
    (tmp_path / "a.json").write_text(res.stdout)
    twin = {**got, "methods": {"tiny2": "pretrained:tiny"},
            "rows": [{**r, "method": "tiny2"} for r in got["rows"] if r["method"] == "tiny"],
            "scene_rows": [{**r, "method": "tiny2"} for r in got["scene_rows"]
                           if r["method"] == "tiny"]}
    (tmp_path / "b.json").write_text(json.dumps(twin))
    merged = _benchmark(["--merge", str(tmp_path / "a.json"), str(tmp_path / "b.json"),
                         "--seed-group", "T=tiny,tiny2", "--json"], reg)
    assert merged.returncode == 0, merged.stderr[-2000:]
    m = json.loads(merged.stdout)
    assert list(m["methods"]) == ["constvel", "logreplay", "tiny", "tiny2"]
    assert list(m["intervals"]) == ["T", "constvel", "logreplay"]
    assert m["intervals"]["T"]["members"] == ["tiny", "tiny2"]
    assert m["intervals"]["T"]["figures"]["realism_meta_metric"]["mean"] == pytest.approx(
        rows[("tiny", "realism_meta_metric")]["mean"], abs=1e-12)
    again = _benchmark(["--merge", str(tmp_path / "a.json"), str(tmp_path / "a.json")], reg)
    assert again.returncode != 0 and "method 'constvel' is also in another file" in again.stderr
    # a seed group must name --policy names, each in one group
    for group, problem in (("G=tiny,nope", "'nope' is not a --policy name"),
                           ("G", "expected NAME=P1,P2")):
        bad = _benchmark(["--policy", "tiny=pretrained:tiny", "--seed-group", group,
                          "--scenes", str(HELD_OUT), "--out", str(tmp_path / "q3")], reg)
        assert bad.returncode != 0 and problem in bad.stderr and not (tmp_path / "q3").exists()
    # a policy is never scored on a scene it was trained on
    res = _benchmark(["--policy", "tiny=pretrained:tiny", "--baselines", "--scenes", SCENE,
                      "--seeds", "0", "--rollouts", "2", "--out", str(tmp_path / "q2")], reg)
    assert res.returncode == 1
    assert res.stderr.strip().splitlines()[-1] == (
        f"error: policy tiny was trained on scene {SID}, which is scored here "
        "(--allow-trained-scenes marks such scenes instead)")
    assert not (tmp_path / "q2").exists()
