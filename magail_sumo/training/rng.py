"""The global RNG states of a run (torch / numpy / python) and their checkpoint form.

:func:`rng_state` gives the states as the libraries hand them (numpy's legacy tuple, python's
tuple); :func:`encode_rng` turns them into tensors and plain data (``torch.load(weights_only=True)``
safe) and :func:`decode_rng` back, bit for bit, refusing malformed input with ValueError /
TypeError; :func:`set_rng_state` restores them; :func:`seed_everything` seeds all three.
"""

from __future__ import annotations

import random
from typing import Any

import numpy as np
import torch


def rng_state() -> dict:
    """The torch / numpy / python global RNG states (numpy's as it gives them)."""
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(),
            "python": random.getstate()}


def encode_rng(state: dict) -> dict:
    """:func:`rng_state` as tensors and plain data."""
    name, keys, pos, has_gauss, cached = state["numpy"]
    version, internal, gauss = state["python"]
    return {"torch": state["torch"],
            "numpy": [str(name), torch.from_numpy(np.asarray(keys, np.uint32).astype(np.int64)),
                      int(pos), int(has_gauss), float(cached)],
            "python": [int(version), [int(v) for v in internal], gauss]}


def decode_rng(state: Any) -> dict:
    """:func:`encode_rng`'s form back to :func:`rng_state`'s (ValueError / TypeError when
    malformed)."""
    if not isinstance(state, dict):
        raise TypeError("rng is not a mapping")
    t = state["torch"]
    if not isinstance(t, torch.Tensor) or t.dtype != torch.uint8 or t.dim() != 1:
        raise TypeError("rng.torch is not a byte tensor")
    name, keys, pos, has_gauss, cached = state["numpy"]
    if not isinstance(keys, torch.Tensor) or keys.shape != (624,):
        raise ValueError("rng.numpy keys are not 624 integers")
    keys = keys.numpy()
    if keys.min() < 0 or keys.max() >= 1 << 32:
        raise ValueError("rng.numpy keys out of range")
    version, internal, gauss = state["python"]
    if not (isinstance(internal, (list, tuple)) and all(type(v) is int for v in internal)):
        raise TypeError("rng.python state is not a list of integers")
    if not (isinstance(pos, int) and isinstance(has_gauss, int)
            and isinstance(cached, (int, float)) and (gauss is None or isinstance(gauss, float))):
        raise TypeError("rng fields have wrong types")
    return {"torch": t, "numpy": (str(name), keys.astype(np.uint32), pos, has_gauss, float(cached)),
            "python": (version, tuple(internal), gauss)}


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
