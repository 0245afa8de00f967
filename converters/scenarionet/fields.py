"""Field coercion of the ScenarioNet reader: every value read from a scenario dict is checked
and converted here, and a wrong shape or type raises a
:class:`~magail_sumo.scene.SceneValidationError` naming the key path (``path``) and what was
found (:func:`describe`, one short line, never a deep repr).

The scene's memory is budgeted while it is read (:func:`memory_budget`, charged by
:func:`charge` before lists, tracks and polylines are allocated). :mod:`.reader` builds the
:class:`~magail_sumo.scene.Scene` from these values.
"""

from __future__ import annotations

import contextlib
import contextvars
from typing import Any, Iterator

import numpy as np

from magail_sumo.outputs import printable
from magail_sumo.scene import SceneValidationError

_INT64 = (-(1 << 63), (1 << 63) - 1)
#: (limit, bytes left) of memory the scene being read may still take (None: unlimited). A pickle
#: can reference one array or list from many places (its memo), so a small file can describe a
#: huge scene; :func:`~converters.scenarionet.reader.load_scenarionet` sets the same budget as
#: the unpickler's (:func:`~converters.scenarionet.safe_pickle.allocation_budget` of the file
#: size) through :func:`memory_budget`.
_BUDGET: contextvars.ContextVar[list[int] | None] = contextvars.ContextVar("budget", default=None)
PER_ITEM = 64  # bytes charged per list item / per track state
_F32_MAX = float(np.finfo(np.float32).max)


def describe(value: Any) -> str:
    """A short one-line rendering of ``value`` for a message (never a deep or huge repr)."""
    if type(value) is str and len(value) <= 40 and value.isprintable():
        return repr(value)  # fast path: dict keys of real files
    if isinstance(value, (str, bytes, int, float, bool, type(None), np.number, np.bool_)):
        try:
            return printable(repr(value), 60)
        except ValueError:  # an int too large to print
            return f"an int of {value.bit_length()} bits"  # type: ignore[union-attr]
    if isinstance(value, np.ndarray):
        return f"an array of shape {value.shape}"
    name = type(value).__name__
    return f"{'an' if name[:1] in 'aeiou' else 'a'} {name}"


@contextlib.contextmanager
def memory_budget(budget: int | None) -> Iterator[None]:
    """Budget ``budget`` bytes (None: unlimited) for the scene read inside the block."""
    token = _BUDGET.set(None if budget is None else [budget, budget])
    try:
        yield
    finally:
        _BUDGET.reset(token)


def charge(nbytes: int, path: str) -> None:
    """Take ``nbytes`` off the budget (:func:`memory_budget`); an error naming ``path`` when it
    runs out."""
    budget = _BUDGET.get()
    if budget is None:
        return
    budget[1] -= nbytes
    if budget[1] < 0:
        raise SceneValidationError(
            f"{path}: the scene would take more than {budget[0]} bytes of memory (the limit for "
            "this file's size; its arrays or lists are shared between many fields)")


def required(d: Any, key: str, path: str) -> Any:
    """``d[key]``; an error when ``d`` is not a dict or lacks ``key``."""
    where = f"{path}: " if path else ""
    if not isinstance(d, dict):
        raise SceneValidationError(f"{where}expected a dict, got {type(d).__name__}")
    if key not in d:
        raise SceneValidationError(f"{where}missing key '{key}'")
    return d[key]


def as_array(value: Any, shape: tuple[int, ...], dtype: Any, path: str) -> np.ndarray:
    """``value`` as a numeric array of ``dtype`` and ``shape`` (-1: any size; a (T, 1) array
    stands for (T,)); a float64 narrowed to float32 must stay finite."""
    try:
        arr = np.asarray(value)
        kind = arr.dtype.kind
        if kind not in "biuf":
            raise TypeError(f"dtype {arr.dtype}")
        narrowing = dtype is np.float32 and kind == "f" and arr.dtype.itemsize > 4
        if narrowing:
            with np.errstate(over="ignore"):  # overflow is reported below
                out = arr.astype(dtype)
        else:
            out = arr.astype(dtype, copy=False)
    except (TypeError, ValueError, OverflowError, RecursionError) as exc:
        raise SceneValidationError(f"{path}: expected a numeric array "
                                   f"({printable(str(exc), 80)})") from None
    if narrowing and out.size:
        over = np.isinf(out) & ~np.isinf(arr)  # finite in the file, too large for float32
        if over.any():
            k = int(np.flatnonzero(over.reshape(-1))[0])
            raise SceneValidationError(
                f"{path}: value {arr.reshape(-1)[k]:.6g} out of range (|value| > {_F32_MAX:.4g})")
    arr = out
    if len(shape) == 1 and arr.ndim == 2 and arr.shape[1] == 1:
        arr = arr[:, 0]  # (T, 1) variants written by some converters
    if arr.ndim != len(shape) or any(s not in (-1, n) for s, n in zip(shape, arr.shape)):
        raise SceneValidationError(f"{path}: expected shape {shape}, got {arr.shape}")
    return arr


def as_int(value: Any, path: str) -> int:
    """An integer within 64 bits (an int, a numpy integer or a decimal string; no bool)."""
    kind = type(value)
    if kind is int:  # fast path: most ids and indices
        out = value
    else:
        try:
            if kind is not str and (isinstance(value, (bool, np.bool_))
                                    or not isinstance(value, (int, str, np.integer))):
                raise ValueError
            out = int(value)  # ScenarioNet stores some ids as decimal strings
        except (TypeError, ValueError, OverflowError):
            raise SceneValidationError(f"{path}: expected an integer, got {describe(value)}") \
                from None
    if not _INT64[0] <= out <= _INT64[1]:
        raise SceneValidationError(f"{path}: integer {describe(out)} out of range (64-bit)")
    return out


def as_float(value: Any, path: str) -> float:
    """A finite number (no bool)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        raise SceneValidationError(f"{path}: expected a number, got {describe(value)}")
    try:
        out = float(value)
    except OverflowError:
        raise SceneValidationError(f"{path}: number {describe(value)} out of range") from None
    if not np.isfinite(out):
        raise SceneValidationError(f"{path}: expected a finite number, got {out}")
    return out


def or_default(value: Any, default: Any) -> Any:
    """``default`` for None (as ``value or default`` did, without truth-testing arrays)."""
    return default if value is None else value


def as_bool(value: Any, path: str) -> bool:
    """A bool (or an integer taken as one)."""
    if not isinstance(value, (bool, int, np.bool_, np.integer)):
        raise SceneValidationError(f"{path}: expected a bool, got {describe(value)}")
    return bool(value)


def as_list(value: Any, path: str) -> list:
    """The items of a list-like field (None: empty)."""
    if value is None:
        return []
    if isinstance(value, np.ndarray):
        if value.ndim != 1:
            raise SceneValidationError(f"{path}: expected a list, got an array of shape "
                                       f"{value.shape}")
        charge(PER_ITEM * len(value), path)
        return value.tolist()
    if not isinstance(value, (list, tuple)):
        raise SceneValidationError(f"{path}: expected a list, got {describe(value)}")
    charge(PER_ITEM * len(value), path)
    return list(value)


def as_text(value: Any, path: str) -> str:
    """A string (an integer is written out; no bool)."""
    if isinstance(value, bool) or not isinstance(value, (str, int, np.integer)):
        raise SceneValidationError(f"{path}: expected a string, got {describe(value)}")
    return str(value)


def as_enum(value: Any, table: dict, path: str):
    """``table[value]``; an error naming an unknown type name."""
    try:
        return table[value]
    except (KeyError, TypeError):
        if not isinstance(value, (str, int, type(None))):
            raise SceneValidationError(f"{path}: expected a type name, got {describe(value)}") \
                from None
        raise SceneValidationError(f"{path}: unknown type {describe(value)}") from None


def _decimal(text: str) -> bool:
    try:
        int(text)
    except ValueError:
        return False
    return True


def _key_int(key: Any, path: str) -> int:
    if type(key) is str and 0 < len(key) < 19 and key.isdigit() and key.isascii():
        return int(key)  # fast path: the decimal keys of real files (always within int64)
    return as_int(key, f"{path}[{describe(key)}] key")


class Ids:
    """Integer ids of a dict's keys: the keys themselves when every key is an integer (or a
    decimal string), else 0..n-1 in recorded order with the original keys kept as names."""

    def __init__(self, keys: list, path: str) -> None:
        self.names: list[str] | None = None
        try:
            self.ids = [_key_int(k, path) for k in keys]
            return
        except SceneValidationError:
            if not any(type(k) is str and not _decimal(k) for k in keys):
                raise  # a bad integer key (a float, a bool, out of range): refused as before
        self.names = [as_text(k, f"{path}[{describe(k)}] key") for k in keys]
        self.ids = list(range(len(keys)))
        self.by_name = {name: i for i, name in enumerate(self.names)}

    @property
    def renumbered(self) -> bool:
        return self.names is not None

    def pairs(self) -> tuple[tuple[int, str], ...]:
        return tuple(enumerate(self.names)) if self.names is not None else ()

    def resolve(self, value: Any, path: str) -> tuple[int | None, str]:
        """``(our id or None when the source's id is unknown, the id as in the source)``."""
        if self.names is None:
            v = as_int(value, path)
            return v, str(v)
        name = as_text(value, path)
        return self.by_name.get(name), name


def as_points(value: Any, path: str) -> np.ndarray:
    """(N, 3) float64 points of a polyline or polygon (2 columns: z = 0)."""
    arr = as_array(value, (-1, -1), np.float64, path)
    charge(2 * 24 * arr.shape[0], path)
    if arr.shape[1] == 2:
        arr = np.concatenate([arr, np.zeros((arr.shape[0], 1))], axis=1)
    elif arr.shape[1] != 3:
        raise SceneValidationError(f"{path}: expected 2 or 3 columns, got {arr.shape[1]}")
    return arr


def as_int_array(value: Any, length: int, path: str) -> np.ndarray:
    """(length,) int64 of whole numbers within 64 bits (floats are accepted when integral)."""
    arr = as_array(value, (length,), np.float64, path) if not (
        isinstance(value, np.ndarray) and value.dtype.kind in "iub") else \
        as_array(value, (length,), np.int64, path)
    if arr.dtype.kind == "f":
        bad = ~np.isfinite(arr) | (arr != np.round(arr)) | (np.abs(arr) >= 2.0 ** 63)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise SceneValidationError(f"{path}[{k}]: expected an integer, got {float(arr[k]):.6g}")
        arr = arr.astype(np.int64)
    return arr
