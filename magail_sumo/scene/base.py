"""Shared machinery of the scene dataclasses: value equality over numpy fields."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np


def values_equal(a: Any, b: Any) -> bool:
    """Exact equality that understands numpy arrays and nested tuples of them.

    Arrays are equal when shape, dtype kind and every element are equal (NaN never equals).
    """
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if not (isinstance(a, np.ndarray) and isinstance(b, np.ndarray)):
            return False
        return a.shape == b.shape and a.dtype.kind == b.dtype.kind and bool(np.array_equal(a, b))
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(values_equal(x, y) for x, y in zip(a, b))
    return bool(a == b)


class ArrayDataclass:
    """Mixin giving frozen dataclasses with numpy fields value equality.

    Dataclasses using it are declared with ``eq=False`` so that this ``__eq__`` is kept.
    """

    __hash__ = None  # type: ignore[assignment]  # mutable arrays inside: not hashable

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(
            values_equal(getattr(self, f.name), getattr(other, f.name))
            for f in dataclasses.fields(self)  # type: ignore[arg-type]
            if f.compare
        )

    def differences(self, other: "ArrayDataclass", prefix: str = "") -> list[str]:
        """Names of the fields (dotted paths) whose values differ; for test messages."""
        out: list[str] = []
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            if not f.compare:
                continue
            a, b = getattr(self, f.name), getattr(other, f.name)
            name = f"{prefix}{f.name}"
            if isinstance(a, ArrayDataclass) and type(a) is type(b):
                out.extend(a.differences(b, prefix=name + "."))
            elif not values_equal(a, b):
                out.append(name)
        return out


def frozen_array(values: Any, dtype: Any, shape: tuple[int, ...] | None = None) -> np.ndarray:
    """A read-only contiguous array of ``dtype``; checks ``shape`` when given (-1 = any)."""
    arr = np.ascontiguousarray(values, dtype=dtype)
    if shape is not None:
        if arr.ndim != len(shape) or any(s != -1 and s != n for s, n in zip(shape, arr.shape)):
            raise ValueError(f"expected shape {shape}, got {arr.shape}")
    arr.setflags(write=False)
    return arr
