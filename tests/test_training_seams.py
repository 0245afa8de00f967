"""Training seams: algorithms registered by name, dispatched by ``train``; shared RNG and
checkpoint helpers in their own modules."""

from __future__ import annotations

import random

import numpy as np
import pytest
import torch

from magail_sumo.config import ConfigError, from_dict
from magail_sumo.training import algorithms
from magail_sumo.training.config import TrainConfig
from magail_sumo.training.rng import decode_rng, encode_rng, rng_state, set_rng_state


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
