"""Strict YAML configs: unknown keys and wrong types are refused, naming file and key."""

from __future__ import annotations

import json
from pathlib import Path
from dataclasses import dataclass, field
from typing import Literal

import pytest

from magail_sumo.config import ConfigError, load_config, record_run, to_dict


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
    with pytest.raises(ConfigError, match="nope.yaml: cannot read"):
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
