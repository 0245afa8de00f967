"""Configs: strict YAML (unknown keys, wrong types, duplicate keys and aliases refused, naming
file and key), training configs range-checked at load time with one-line errors naming the
file and the dotted key before any set-up, the run record, and every shipped config."""

from __future__ import annotations

import json
import time
from pathlib import Path
from dataclasses import dataclass, field
from typing import Literal

import pytest

from conftest import WOMD_DIR
from magail_sumo.cli.main import main
from magail_sumo.config import (
    MAX_MESSAGE, ConfigError, from_dict, load_config, record_run, to_dict,
)
from magail_sumo.training.config import TrainConfig
from magail_sumo.training.preflight import check_train_config


@dataclass(frozen=True)
class Inner:
    lr: float = 1e-3
    layers: tuple[int, ...] = (64, 64)


@dataclass(frozen=True)
class Outer:
    seed: int = 0
    pooling: Literal["mean", "cls"] = "mean"
    name: str | None = None
    inner: Inner = field(default_factory=Inner)


def test_load_nested_and_defaults(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("seed: 3\ninner:\n  lr: 2\n  layers: [32, 16]\n")
    cfg = load_config(p, Outer)
    assert cfg == Outer(seed=3, inner=Inner(lr=2.0, layers=(32, 16)))
    assert to_dict(cfg)["inner"]["layers"] == [32, 16]


@pytest.mark.parametrize("text, message", [
    ("sed: 3\n", "c.yaml: sed: unknown key"),
    ("inner:\n  learning_rate: 1\n", "c.yaml: inner.learning_rate: unknown key"),
    ("seed: three\n", "c.yaml: seed: expected an integer, got 'three'"),
    ("seed: 1.5\n", "c.yaml: seed: expected an integer"),
    ("inner:\n  lr: [1]\n", "c.yaml: inner.lr: expected a number"),
    ("pooling: max\n", "c.yaml: pooling: 'max' is not one of"),
    ("inner: 5\n", "c.yaml: inner: expected a mapping"),
    ("seed: [\n", "c.yaml: not valid YAML"),
])
def test_bad_configs_are_refused_with_the_key(tmp_path, text, message):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=message.replace("[", r"\[")):
        load_config(p, Outer)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="nope.yaml: no such file"):
        load_config(tmp_path / "nope.yaml", Outer)


def test_record_run(tmp_path):
    d = record_run(tmp_path / "run", Outer(seed=7))
    assert "seed: 7" in (d / "config.yaml").read_text()
    env = json.loads((d / "environment.json").read_text())
    assert env["versions"]["numpy"] != "not installed" and "git_commit" in env
    assert load_config(d / "config.yaml", Outer) == Outer(seed=7)


CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.mark.parametrize("name", sorted(str(p.relative_to(CONFIGS)) for p in CONFIGS.rglob("*.yaml")
                                        if p.parent.name != "splits"))
def test_every_shipped_config_loads(name):
    """Every training config (the experiments, demo.yaml, and the algorithm and scene files
    they are composed of) loads on its own."""
    from magail_sumo.training.config import TrainConfig

    cfg = load_config(CONFIGS / name, TrainConfig)
    assert cfg.updates >= 1 or cfg.algorithm == "bc"


# -------------------------------------- training configs: ranges, strict YAML, checks before set-up
SCENE = str(WOMD_DIR / "850c48d8bbfa008f.tfrecord")  # 91 steps


def _refused(tmp_path: Path, text: str, pattern: str) -> str:
    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=pattern) as exc:
        load_config(p, TrainConfig)
    msg = str(exc.value)
    assert msg.startswith(f"{p}: ") and "\n" not in msg and len(msg) <= MAX_MESSAGE
    return msg


@pytest.mark.parametrize("text, pattern", [
    ("ppo:\n  n_steps: 0\n", r"ppo\.n_steps: must be >= 1, got 0"),
    ("ppo:\n  learning_rate: -1\n", r"ppo\.learning_rate: must be > 0"),
    ("ppo:\n  learning_rate: .nan\n", r"ppo\.learning_rate: expected a finite number"),
    ("ppo:\n  learning_rate: .inf\n", r"ppo\.learning_rate: expected a finite number"),
    ("discriminator:\n  learning_rate: -1\n", r"discriminator\.learning_rate: must be > 0"),
    ("bc:\n  learning_rate: .inf\n", r"bc\.learning_rate: expected a finite number"),
    ("ppo:\n  batch_size: 0\n", r"ppo\.batch_size: must be >= 1"),
    ("discriminator:\n  batch_size: 0\n", r"discriminator\.batch_size: must be > 0"),
    ("bc:\n  batch_size: 0\n", r"bc\.batch_size: must be > 0"),
    ("ppo:\n  n_epochs: -3\n", r"ppo\.n_epochs: must be >= 1, got -3"),
    ("discriminator:\n  transformer:\n    embed_dim: 10\n    num_heads: 4\n",
     r"discriminator\.transformer\.num_heads: must divide embed_dim \(10\)"),
    ("policy:\n  critic: transformer\n  critic_transformer:\n    embed_dim: 10\n    num_heads: 3\n",
     r"policy\.critic_transformer\.num_heads: must divide embed_dim \(10\)"),
    ("scenes:\n  files: []\n", r"scenes\.files: needs at least one scene file"),
    ("ppo:\n  clip_range: -0.2\n", r"ppo\.clip_range: must be in \(0, 1\]"),
    ("ppo:\n  lr_min: 0.01\n  lr_max: 0.001\n", r"ppo\.lr_max: must be >= lr_min"),
    ("env:\n  max_steps: -1\n", r"env\.max_steps: must be >= 1"),
    ("env:\n  start_step: -1\n", r"env\.start_step: must be >= 0"),
    ("env:\n  limits:\n    max_speed: 0\n", r"env\.limits\.max_speed: must be > 0"),
    ("scenes:\n  worker_timeout_s: 0\n", r"scenes\.worker_timeout_s: must be > 0"),
    ("device: gpu-ish\n", r"device: not a torch device"),
    ("updates: -1\n", r"updates: must be >= 0"),
    ("seed: -5\n", r"seed: must be in"),
    ("ppo:\n  gamma: 1.5\n", r"ppo\.gamma: must be in \[0, 1\]"),
    ("discriminator:\n  ignore_features: [prev_acel]\n",
     r"discriminator\.ignore_features: unknown observation feature\(s\) \['prev_acel'\]"),
])
def test_out_of_range_values_refused_naming_file_and_key(tmp_path, text, pattern):
    _refused(tmp_path, text, pattern)


def test_range_rules_hold_for_every_loader():
    with pytest.raises(ConfigError, match=r"ppo\.n_steps: must be >= 1"):
        from_dict(TrainConfig, {"ppo": {"n_steps": 0}})


def test_duplicate_keys_refused(tmp_path):
    _refused(tmp_path, "seed: 1\nppo:\n  n_steps: 8\n  n_steps: 16\n",
             r"duplicate key 'n_steps' \(line 4, column 3\)")


def test_aliases_refused_quickly_with_a_short_message(tmp_path):
    lol = ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i, (prev, cur) in enumerate(zip("abcdefgh", "bcdefghi")):
        lol.append(f"{cur}: &{cur} [" + ",".join([f"*{prev}"] * 9) + "]")
    text = "\n".join(lol) + "\n"
    assert len(text) < 400
    t0 = time.perf_counter()
    _refused(tmp_path, text, r"not valid YAML \(aliases \(\*a\) are not allowed")
    # a generous bound (well under 0.1 s here): expanding the 9**9 aliases takes minutes
    assert time.perf_counter() - t0 < 30.0


def test_binary_and_huge_files_refused(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_bytes(b"seed: 1\n\xff\xfe\x00garbage\x80\n")
    with pytest.raises(ConfigError, match=r"c\.yaml: not UTF-8 text \(byte 0xff at offset 8\)"):
        load_config(p, TrainConfig)
    p.write_text("seed: 1\n" + "#" * (2 << 20) + "\n")
    with pytest.raises(ConfigError, match="too large"):
        load_config(p, TrainConfig)


def test_long_values_are_truncated_in_messages(tmp_path):
    msg = _refused(tmp_path, "seed: '" + "x" * 100_000 + "'\n", r"seed: expected an integer")
    assert len(msg) < 300
    msg = _refused(tmp_path, '? "' + "k\\n" * 5000 + '"\n: 1\n', r"unknown key")
    assert len(msg) <= MAX_MESSAGE


def _cli_refused(tmp_path, capsys, monkeypatch, text: str, *needles: str) -> str:
    from magail_sumo.training import trainer

    def set_up(*args, **kwargs):  # before any set-up: train() is never reached
        raise AssertionError("training was set up")

    monkeypatch.setattr(trainer, "train", set_up)
    p = tmp_path / "c.yaml"
    p.write_text(text)
    assert main(["train", "--config", str(p), "--run-dir", str(tmp_path / "run")]) == 1
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    for n in (str(p),) + needles:
        assert n in lines[0], lines[0]
    assert not (tmp_path / "run").exists()
    return lines[0]


def test_start_step_past_the_scene_refused_before_set_up(tmp_path, capsys, monkeypatch):
    _cli_refused(tmp_path, capsys, monkeypatch, f"scenes:\n  files: ['{SCENE}']\nenv:\n  start_step: 95\n",
                 "env.start_step: 95", "91 steps")


def test_missing_scene_file_named(tmp_path, capsys, monkeypatch):
    _cli_refused(tmp_path, capsys, monkeypatch, f"scenes:\n  files: ['{SCENE}', 'nope/gone.tfrecord']\n",
                 "scenes.files[1]", "nope/gone.tfrecord", "no such file")


def test_unavailable_device_refused(tmp_path, capsys, monkeypatch):
    import torch

    n = torch.cuda.device_count() if torch.cuda.is_available() else 0
    _cli_refused(tmp_path, capsys, monkeypatch, f"device: cuda:{n + 7}\nscenes:\n  files: ['{SCENE}']\n",
                 f"device: 'cuda:{n + 7}'")


def test_check_train_config_accepts_the_defaults_and_bundled_scenes():
    check_train_config(from_dict(TrainConfig, {"scenes": {"files": [SCENE]}}), "x.yaml")


@pytest.mark.sumo
def test_batch_size_larger_than_the_rollout_refused(bundled_networks):
    from magail_sumo.training.trainer import GailRun

    cfg = from_dict(TrainConfig, {
        "env": {"max_steps": 10, "controlled": 2},
        "scenes": {"files": [SCENE], "networks": str(bundled_networks(Path(SCENE).stem))},
        "discriminator": {"kind": "mlp", "mlp_hidden": [8]},
        "ppo": {"n_steps": 4, "batch_size": 4096}})
    with pytest.raises(ConfigError, match=r"ppo\.batch_size: 4096 is larger than a rollout "
                                          r"\(ppo\.n_steps 4 x \d+ agent slots"):
        GailRun(cfg, None)


def test_config_that_is_a_fifo_or_device_is_refused_at_once(tmp_path):
    """A FIFO would block ``open`` forever and a device stream: one line, in seconds."""
    import os

    fifo = tmp_path / "train.yaml"
    os.mkfifo(fifo)
    dev = tmp_path / "zero.yaml"
    dev.symlink_to("/dev/zero")
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match=r"train.yaml: is a FIFO \(named pipe\)"):
        load_config(fifo, TrainConfig)
    with pytest.raises(ConfigError, match=r"zero.yaml: is a character device"):
        load_config(dev, TrainConfig)
    assert time.monotonic() - t0 < 5
