"""A restricted unpickler: loads plain data (builtins containers, numpy arrays) and nothing else.

Loading a pickle can run arbitrary code through the globals it names. This unpickler resolves
only an allowlist of data types; any other global (``os.system``, a user class, even
``numpy.load``) is refused with :class:`UnsafePickleError` before anything is called.

Even allowlisted callables are never handed to the file as they are: each is a wrapper that
checks its arguments first, so that a pickle can neither corrupt memory nor make the reader
allocate far more than the file holds.

* **No object arrays.** A dtype holding Python objects (``dtype('O')``, a structured dtype with
  an object field, numpy 2's ``StringDType``) is refused wherever it is used: such an array
  built from the file's bytes would take its element pointers from the file (a crafted
  111-byte pickle segfaults the interpreter). Structured dtypes must keep every field inside
  the item (``dtype.__setstate__`` does not check offsets).
* **Arrays only through numpy's own pickle path.** ``numpy.ndarray`` may be *named* (numpy
  pickles pass it to ``_reconstruct``) but not called: direct construction
  ``ndarray(shape, dtype, buffer, offset, strides)`` reads memory the file describes. Arrays are
  built by ``_reconstruct`` followed by ``__setstate__`` (checked: dtype, shape, and a data
  string of exactly the array's size) or by ``_frombuffer`` (protocol 5, checked likewise).
* **Allocation budget.** Everything the allowlisted callables create (arrays,
  ``bytes``/``bytearray``/``str``, containers built from a ``range``) is charged against a
  budget of :func:`allocation_budget` bytes: ``max(64 MiB, 64 x file size)``. Real scenario
  pickles build arrays from their own bytes (about 1x their size); a file needing more than 64
  times its size is refused (a 48-byte ``bytearray(4e9)`` pickle, or stride-0 arrays growing
  with a number in the file). The pickle is read into memory first (its size is known), so a
  length field claiming more bytes than the file has is "truncated", never allocated.
* **Codecs.** ``_codecs.encode`` (protocol <= 2 spelling of ``bytes``) is limited to
  ``latin-1`` / ``utf-8`` / ``ascii`` text.

Any refusal raises :class:`UnsafePickleError` (nothing was executed); a pickle that is merely
malformed raises :class:`pickle.UnpicklingError` or one of the errors listed in
:data:`LOAD_ERRORS`, all with one-line messages.
"""

from __future__ import annotations

import _compat_pickle
import builtins
import codecs
import collections
import io
import math
import os
import pickle
from typing import Any, BinaryIO, Callable

import numpy as np

_NUMPY_CORE = getattr(np, "_core", None) or np.core  # numpy 1 vs 2

#: smallest allocation budget of one file, bytes
MIN_BUDGET = 64 << 20
#: allocation budget per byte of file
BUDGET_PER_BYTE = 64
#: exceptions a malformed (not unsafe) pickle may raise while loading
LOAD_ERRORS = (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError,
               IndexError, KeyError, ImportError, OverflowError, MemoryError, RecursionError,
               UnicodeError, LookupError)
#: dtype kinds an array may have (no objects ``O``, no numpy 2 variable-width strings ``T``)
_KINDS = frozenset("biufcmMSUV")
_CODECS = frozenset(("latin1", "latin_1", "latin-1", "iso-8859-1", "iso8859-1", "l1",
                     "utf-8", "utf8", "utf_8", "ascii"))
_POINTER = 8  # bytes charged per element of a container built from an iterable


def allocation_budget(file_size: int) -> int:
    """Bytes a pickle of ``file_size`` bytes may make the unpickler allocate (see module doc)."""
    return max(MIN_BUDGET, BUDGET_PER_BYTE * int(file_size))


class UnsafePickleError(pickle.UnpicklingError):
    """The pickle names a global outside the allowlist, or calls an allowed one with arguments
    that could corrupt memory or exceed the allocation budget; nothing unsafe was executed."""


def check_dtype(dtype: Any, what: str = "array") -> np.dtype:
    """``dtype`` if it is a numpy dtype an array from a file may have; else UnsafePickleError."""
    if not isinstance(dtype, np.dtype):
        raise UnsafePickleError(f"{what}: expected a numpy dtype, got {type(dtype).__name__}")
    if dtype.hasobject or dtype.kind not in _KINDS or dtype.flags & 0x01:  # NPY_ITEM_REFCOUNT
        raise UnsafePickleError(f"{what}: refused dtype {dtype.str!r} "
                                "(arrays of Python objects are not loaded)")
    if dtype.subdtype is not None:
        check_dtype(dtype.subdtype[0], what)
    if dtype.fields:
        for name, spec in dtype.fields.items():
            sub, offset = spec[0], spec[1]
            check_dtype(sub, what)
            if not 0 <= offset <= dtype.itemsize - sub.itemsize:
                raise UnsafePickleError(f"{what}: structured dtype field {str(name)[:40]!r} lies "
                                        f"outside its {dtype.itemsize}-byte item")
    return dtype


def _shape(shape: Any, what: str) -> tuple[int, ...]:
    if type(shape) is tuple and len(shape) <= 32 and all(type(n) is int for n in shape):
        if not shape or min(shape) >= 0:  # fast path: what numpy's own pickles hold
            return shape
    elif isinstance(shape, (int, np.integer)) and not isinstance(shape, bool):
        shape = (shape,)
    if not isinstance(shape, tuple) or len(shape) > 32 or not all(
            isinstance(n, (int, np.integer)) and not isinstance(n, bool) and n >= 0 for n in shape):
        raise UnsafePickleError(f"{what}: bad array shape")
    return tuple(int(n) for n in shape)


class _NdarrayName:
    """Stands for ``numpy.ndarray`` in a pickle: accepted by ``_reconstruct``, not callable."""

    def __new__(cls, *args: Any, **kwargs: Any) -> Any:
        raise UnsafePickleError("refused direct numpy.ndarray(shape, dtype, buffer, ...) "
                                "construction: arrays load only through numpy's pickle path")


class _Budget:
    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.left = limit

    def charge(self, nbytes: int, what: str) -> None:
        self.left -= nbytes
        if self.left < 0:
            raise UnsafePickleError(f"{what} would exceed the allocation budget of this file "
                                    f"({self.limit} bytes; {BUDGET_PER_BYTE}x its size, at least "
                                    f"{MIN_BUDGET >> 20} MiB)")


class _CheckedArray(np.ndarray):
    """An ndarray whose ``__setstate__`` (pickle BUILD) checks dtype, shape and data size."""

    _budget: _Budget | None = None

    def __setstate__(self, state: Any) -> None:
        # Hot path (one call per array of a real file): numpy itself checks the shape and that
        # the data string has exactly the array's size; what it does not check is the dtype.
        if type(state) is not tuple or len(state) not in (4, 5):
            raise UnsafePickleError("array state: expected a 4- or 5-tuple")
        dtype, raw = state[-3], state[-1]
        if not isinstance(dtype, np.dtype) or dtype.fields is not None \
                or dtype.subdtype is not None or dtype.hasobject or dtype.kind not in _KINDS:
            check_dtype(dtype, "array state")  # structured dtypes, or the refusal
        if type(raw) is not bytes and type(raw) is not bytearray:
            raise UnsafePickleError(f"array state: data must be bytes, got {type(raw).__name__}")
        budget = self._budget
        if budget is not None:
            budget.left -= len(raw)
            if budget.left < 0:
                budget.charge(0, "array")
        _ndarray_setstate(self, state)


_ndarray_setstate = np.ndarray.__setstate__


def _sized(value: Any, what: str) -> int:
    try:
        return len(value)
    except TypeError:
        raise UnsafePickleError(f"{what}: refused argument of type {type(value).__name__}") from None


class _RestrictedUnpickler(pickle.Unpickler):
    def __init__(self, fh: BinaryIO, budget: int) -> None:
        super().__init__(fh)
        self._budget = _Budget(budget)
        # a subclass per load so that concurrent loads keep separate budgets
        self._array_cls = type("ndarray", (_CheckedArray,), {"_budget": self._budget})
        self._allowed = self._allowlist()

    # ------------------------------------------------------------ checked callables

    def _allowlist(self) -> dict[tuple[str, str], Any]:
        b = self._budget
        array_cls = self._array_cls

        def reconstruct(subtype: Any, shape: Any, dtype: Any) -> np.ndarray:
            if subtype is not _NdarrayName:
                raise UnsafePickleError("_reconstruct: only numpy.ndarray may be rebuilt")
            # the real shape and dtype come with __setstate__ (checked there); this is the
            # empty placeholder numpy's own pickles create
            return _NUMPY_CORE.multiarray._reconstruct(array_cls, (0,), b"b")

        def scalar(dtype: Any, obj: Any = None) -> Any:
            check_dtype(dtype, "numpy scalar")
            if not isinstance(obj, bytes) or len(obj) != dtype.itemsize:
                raise UnsafePickleError(f"numpy scalar: expected {dtype.itemsize} data bytes")
            return _NUMPY_CORE.multiarray.scalar(dtype, obj)

        def frombuffer(buf: Any, dtype: Any, shape: Any, order: Any) -> np.ndarray:
            check_dtype(dtype, "array")
            shape = _shape(shape, "array")
            if isinstance(buf, pickle.PickleBuffer):
                buf = buf.raw()
            if not isinstance(buf, (bytes, bytearray, memoryview)):
                raise UnsafePickleError(f"array: data must be bytes, got {type(buf).__name__}")
            nbytes = math.prod(shape) * dtype.itemsize
            if memoryview(buf).nbytes != nbytes:
                raise UnsafePickleError(f"array: {memoryview(buf).nbytes} data bytes for an array "
                                        f"of {nbytes} bytes")
            if order not in ("C", "F", "A", "K"):
                raise UnsafePickleError("array: bad order")
            b.charge(nbytes, "array")
            return _NUMPY_CORE.numeric._frombuffer(buf, dtype, shape, order)

        def make_dtype(obj: Any, align: Any = False, copy: Any = False) -> np.dtype:
            if not isinstance(obj, str) or len(obj) > 64:
                raise UnsafePickleError("numpy.dtype: expected a short type code string")
            return check_dtype(np.dtype(obj, bool(align), bool(copy)), "numpy.dtype")

        def dtype_class(cls: type) -> Callable[..., np.dtype]:
            def make(*args: Any, **kwargs: Any) -> np.dtype:
                return check_dtype(cls(*args, **kwargs), cls.__name__)
            return make

        def binary(cls: type) -> Callable[..., Any]:
            def make(source: Any = b"", *args: Any) -> Any:
                if isinstance(source, (int, np.integer)) and not isinstance(source, bool):
                    b.charge(max(int(source), 0), f"{cls.__name__}({int(source)})")
                else:
                    b.charge(_sized(source, cls.__name__) * (4 if isinstance(source, str) else 1),
                             cls.__name__)
                return cls(source, *args)
            return make

        def text(obj: Any = "", *args: Any) -> str:
            if args:
                if not isinstance(obj, (bytes, bytearray)):
                    raise UnsafePickleError("str: decoding needs bytes")
                b.charge(4 * len(obj), "str")
                return str(obj, *args)
            if not isinstance(obj, (str, int, float, bool, type(None))):
                raise UnsafePickleError(f"str: refused argument of type {type(obj).__name__}")
            return str(obj)

        def container(cls: Any) -> Callable[..., Any]:
            def make(*args: Any, **kwargs: Any) -> Any:
                for arg in args:
                    if not callable(arg):  # defaultdict's factory is a checked callable
                        b.charge(_POINTER * _sized(arg, cls.__name__), cls.__name__)
                return cls(*args, **kwargs)
            return make

        def encode(obj: Any, encoding: Any = "utf-8", errors: Any = "strict") -> bytes:
            if not isinstance(obj, str) or not isinstance(encoding, str) \
                    or encoding.lower() not in _CODECS:
                raise UnsafePickleError(f"_codecs.encode: refused codec {str(encoding)[:40]!r} "
                                        "(only latin-1, utf-8 and ascii text)")
            return codecs.encode(obj, encoding, "strict")

        allowed: dict[tuple[str, str], Any] = {}
        for mod in ("numpy.core", "numpy._core"):
            allowed[(f"{mod}.multiarray", "_reconstruct")] = reconstruct
            allowed[(f"{mod}.multiarray", "scalar")] = scalar
            allowed[(f"{mod}.numeric", "_frombuffer")] = frombuffer
        allowed[("numpy", "ndarray")] = _NdarrayName
        allowed[("numpy", "dtype")] = make_dtype
        for name in dir(getattr(np, "dtypes", object())):
            if name.endswith("DType") and name not in ("ObjectDType", "StringDType"):
                allowed[("numpy.dtypes", name)] = dtype_class(getattr(np.dtypes, name))
        for name in ("int", "float", "complex", "bool", "slice", "range"):
            allowed[("builtins", name)] = getattr(builtins, name)  # no allocation beyond input
        allowed[("builtins", "str")] = text
        for name in ("bytes", "bytearray"):
            allowed[("builtins", name)] = binary(getattr(builtins, name))
        for name in ("tuple", "list", "dict", "set", "frozenset"):
            allowed[("builtins", name)] = container(getattr(builtins, name))
        # Real ScenarioNet files hold ``number_summary.num_moving_objects_each_type`` as a
        # ``defaultdict(int)``: a plain data container, allowed together with OrderedDict.
        allowed[("collections", "defaultdict")] = container(collections.defaultdict)
        allowed[("collections", "OrderedDict")] = container(collections.OrderedDict)
        # Protocol <= 2 pickles spell bytes as ``_codecs.encode(str, "latin1")``.
        allowed[("_codecs", "encode")] = encode
        return allowed

    def find_class(self, module: str, name: str) -> Any:
        # Python 2 spellings of protocol <= 2 pickles (__builtin__.long, ...), mapped as pickle does
        if (module, name) in _compat_pickle.NAME_MAPPING:
            module, name = _compat_pickle.NAME_MAPPING[(module, name)]
        elif module in _compat_pickle.IMPORT_MAPPING:
            module = _compat_pickle.IMPORT_MAPPING[module]
        try:
            return self._allowed[(module, name)]
        except (KeyError, TypeError):
            raise UnsafePickleError(
                f"refused to load {str(module)[:80]}.{str(name)[:80]}: only numpy arrays and "
                "builtin containers are allowed"
            ) from None

    def persistent_load(self, pid: Any) -> Any:
        raise UnsafePickleError("refused persistent id in pickle")


def safe_load(fh: BinaryIO, budget: int | None = None) -> Any:
    """Unpickle plain data from a binary file object; see module doc.

    The rest of the file is read into memory first. ``budget`` (bytes) defaults to
    :func:`allocation_budget` of the data's size.
    """
    return safe_loads(fh.read(), budget)


def safe_loads(data: bytes, budget: int | None = None) -> Any:
    """Unpickle plain data from bytes; see module doc."""
    limit = allocation_budget(len(data)) if budget is None else budget
    return _RestrictedUnpickler(io.BytesIO(data), limit).load()


def safe_load_path(path: str | os.PathLike) -> Any:
    """Unpickle plain data from the file at ``path``; see module doc."""
    with open(path, "rb") as fh:
        return safe_load(fh)
