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
  88-byte pickle segfaulted the interpreter).
* **Dtypes are rebuilt, never patched.** ``numpy.dtype(code)`` yields a placeholder; the state
  a BUILD gives it is checked and the dtype built with numpy's validating constructors.
  numpy's own ``dtype.__setstate__`` trusts its argument (a 6-tuple state crashes the
  interpreter, field offsets are not checked) and is never called with data from a file. A
  dtype that is loaded as a value (not used by an array) stays such a placeholder.
* **Arrays only through numpy's own pickle path.** ``numpy.ndarray`` may be *named* (numpy
  pickles pass it to ``_reconstruct``) but not called: direct construction
  ``ndarray(shape, dtype, buffer, offset, strides)`` reads memory the file describes. Arrays are
  built by ``_reconstruct`` followed by ``__setstate__`` (checked: dtype, and bytes data, whose
  size numpy checks against the shape) or by ``_frombuffer`` (protocol 5, checked likewise).
  Numpy scalars load as the equivalent Python values (``float``, ``int``, ``bytes``...), so no
  numpy object with an unchecked ``__setstate__`` is ever reachable by a BUILD.
* **Allocation budget.** Everything the allowlisted callables create (arrays,
  ``bytes``/``bytearray``/``str``, containers built from a ``range``) is charged against a
  budget of :func:`allocation_budget` bytes: ``max(64 MiB, 64 x file size)``. Real scenario
  pickles build arrays from their own bytes (about 1x their size); a file needing more than 64
  times its size is refused (a 48-byte ``bytearray(4e9)`` pickle, or stride-0 arrays growing
  with a number in the file). The reader applies the same budget to the scene it builds
  (:func:`converters.scenarionet.reader.scene_from_scenarionet`), since the pickle memo lets
  one array or list be referenced from any number of places.
* **No allocation ahead of the data.** The pickle is read into memory and scanned once
  (:func:`_scan`) before CPython's C unpickler sees it: a memo index (PUT / LONG_BINPUT) larger
  than the file (the C unpickler would allocate and zero 16 bytes per index: 1 GB for a
  9-byte pickle) is refused, and a counted length (BINBYTES8, BYTEARRAY8, FRAME...) larger
  than the rest of the file is "truncated" instead of a preallocation.
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
import pickletools
import re
from typing import Any, BinaryIO, Callable

import numpy as np

from magail_sumo.inputs import open_regular

_NUMPY_CORE = getattr(np, "_core", None) or np.core  # numpy 1 vs 2

#: smallest allocation budget of one file, bytes
MIN_BUDGET = 64 << 20
#: allocation budget per byte of file
BUDGET_PER_BYTE = 64
#: exceptions a malformed (not unsafe) pickle may raise while loading
LOAD_ERRORS = (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError,
               IndexError, KeyError, ImportError, OverflowError, MemoryError, RecursionError,
               UnicodeError, LookupError, SyntaxError)
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


_BYTEORDERS = frozenset("<>|=")
_TIME_UNITS = frozenset(("Y", "M", "W", "D", "h", "m", "s", "ms", "us", "ns", "ps", "fs", "as",
                         "generic"))


class _DtypeSpec:
    """What a pickle's ``numpy.dtype(code, align, copy)`` + BUILD describe, resolved later.

    numpy's ``dtype.__setstate__`` trusts its argument (a 6-tuple crashes the interpreter;
    field offsets are not checked), so it is never called with data from a file: the state is
    kept here and :meth:`resolve` builds the dtype with numpy's checked constructors
    (``np.dtype(dict)``, ``np.dtype((base, shape))``, ``newbyteorder``), then
    :func:`check_dtype`.
    """

    __slots__ = ("base", "state", "_dtype")

    def __init__(self, base: np.dtype) -> None:
        self.base = base
        self.state: Any = None
        self._dtype: np.dtype | None = None

    def __setstate__(self, state: Any) -> None:
        self.state = state
        self._dtype = None

    def resolve(self, depth: int = 0) -> np.dtype:
        if self._dtype is None:
            self._dtype = check_dtype(self._build(depth), "numpy.dtype")
        return self._dtype

    def _build(self, depth: int) -> np.dtype:
        st = self.state
        if st is None:
            return self.base
        if depth > 8:
            raise UnsafePickleError("numpy.dtype: nested too deeply")
        if type(st) is not tuple or len(st) not in (8, 9) or st[0] not in (3, 4):
            raise UnsafePickleError("numpy.dtype: unexpected state")
        order, sub, names, fields, elsize = st[1:6]
        meta = st[8] if len(st) == 9 else None
        if order not in _BYTEORDERS or type(elsize) is not int:
            raise UnsafePickleError("numpy.dtype: bad byte order or item size")
        if sub is not None:
            if type(sub) is not tuple or len(sub) != 2:
                raise UnsafePickleError("numpy.dtype: bad subarray")
            shape = _shape(sub[1], "numpy.dtype subarray")
            if math.prod(shape) > 1 << 24:
                raise UnsafePickleError("numpy.dtype: subarray too large")
            return np.dtype((resolve_dtype(sub[0], depth + 1), shape))
        if names is not None or fields is not None:
            if type(names) is not tuple or type(fields) is not dict or len(names) > 4096 \
                    or not all(type(n) is str for n in names):
                raise UnsafePickleError("numpy.dtype: bad field names")
            formats, offsets, titles = [], [], []
            for name in names:
                entry = fields.get(name)
                if type(entry) is not tuple or len(entry) not in (2, 3) \
                        or type(entry[1]) is not int or (len(entry) == 3 and
                                                         type(entry[2]) not in (str, type(None))):
                    raise UnsafePickleError(f"numpy.dtype: bad field {name[:40]!r}")
                formats.append(resolve_dtype(entry[0], depth + 1))
                offsets.append(entry[1])
                titles.append(entry[2] if len(entry) == 3 else None)
            return np.dtype({"names": list(names), "formats": formats, "offsets": offsets,
                             "titles": titles, "itemsize": elsize})
        d = self.base
        if meta is not None:  # datetime64 / timedelta64 unit: (None, (unit, count, 1, 1))
            if d.kind not in "mM" or type(meta) is not tuple or len(meta) != 2 \
                    or type(meta[1]) is not tuple or len(meta[1]) != 4:
                raise UnsafePickleError("numpy.dtype: unexpected metadata")
            unit, count = meta[1][0], meta[1][1]
            unit = unit.decode("ascii", "replace") if isinstance(unit, bytes) else unit
            if unit not in _TIME_UNITS or type(count) is not int or not 0 < count < 1 << 31:
                raise UnsafePickleError("numpy.dtype: bad time unit")
            d = np.dtype(f"{d.kind}8[{count if count != 1 else ''}{unit}]")
        elif elsize not in (-1, d.itemsize):
            raise UnsafePickleError(f"numpy.dtype: item size {elsize} does not match {d.str!r}")
        if order in "<>" and d.byteorder != "|":
            d = d.newbyteorder(order)
        return d


def resolve_dtype(value: Any, depth: int = 0) -> np.dtype:
    """The dtype a pickle's dtype object stands for (checked); UnsafePickleError otherwise."""
    if isinstance(value, _DtypeSpec):
        return value.resolve(depth)
    raise UnsafePickleError(f"expected a numpy dtype, got {type(value).__name__}")


class _NdarrayName:
    """Stands for ``numpy.ndarray`` in a pickle: accepted by ``_reconstruct``, never called.

    An instance without ``__dict__`` (BUILD cannot set attributes on it) and not a type
    (NEWOBJ refuses it).
    """

    __slots__ = ()

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        raise UnsafePickleError("refused direct numpy.ndarray(shape, dtype, buffer, ...) "
                                "construction: arrays load only through numpy's pickle path")


_NDARRAY = _NdarrayName()


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
        if type(dtype) is not _DtypeSpec:
            raise UnsafePickleError(f"array state: expected a numpy dtype, got "
                                    f"{type(dtype).__name__}")
        dtype = dtype._dtype if dtype._dtype is not None else dtype.resolve()
        state = (*state[:-3], dtype, *state[-2:])
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
            if subtype is not _NDARRAY:
                raise UnsafePickleError("_reconstruct: only numpy.ndarray may be rebuilt")
            # the real shape and dtype come with __setstate__ (checked there); this is the
            # empty placeholder numpy's own pickles create
            return _NUMPY_CORE.multiarray._reconstruct(array_cls, (0,), b"b")

        def scalar(dtype: Any, obj: Any = None) -> Any:
            dtype = resolve_dtype(dtype)
            if not isinstance(obj, bytes) or len(obj) != dtype.itemsize:
                raise UnsafePickleError(f"numpy scalar: expected {dtype.itemsize} data bytes")
            # the Python value (float, int, bytes, ...): a numpy scalar's __setstate__ would be
            # reachable by a later BUILD
            return _NUMPY_CORE.multiarray.scalar(dtype, obj).item()

        def frombuffer(buf: Any, dtype: Any, shape: Any, order: Any) -> np.ndarray:
            dtype = resolve_dtype(dtype)
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
            # viewed as the checked subclass, so that a later BUILD on it is checked too
            return _NUMPY_CORE.numeric._frombuffer(buf, dtype, shape, order).view(array_cls)

        def make_dtype(obj: Any, align: Any = False, copy: Any = False) -> _DtypeSpec:
            if not isinstance(obj, str) or len(obj) > 64:
                raise UnsafePickleError("numpy.dtype: expected a short type code string")
            return _DtypeSpec(check_dtype(np.dtype(obj, bool(align)), "numpy.dtype"))

        def dtype_class(cls: type) -> Callable[..., _DtypeSpec]:
            def make(*args: Any, **kwargs: Any) -> _DtypeSpec:
                if args or kwargs:
                    raise UnsafePickleError(f"{cls.__name__}: arguments refused")
                return _DtypeSpec(check_dtype(cls(), cls.__name__))
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
        allowed[("numpy", "ndarray")] = _NDARRAY
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


def _opcode_tables() -> tuple[re.Pattern, dict[int, tuple[int, bool]], frozenset[int]]:
    """A regex skipping runs of fixed-size opcodes (except memo puts and STOP), the counted
    opcodes (code -> (bytes of the count, signed)) and the newline-terminated ones."""
    fixed: dict[int, list[int]] = {}
    counted: dict[int, tuple[int, bool]] = {}
    line: set[int] = set()
    for op in pickletools.opcodes:
        code, arg = op.code.encode("latin-1")[0], op.arg
        if arg is None or arg.n >= 0:
            if code not in _SCANNED:
                fixed.setdefault(0 if arg is None else arg.n, []).append(code)
        elif arg.n == pickletools.TAKEN_FROM_ARGUMENT1:
            counted[code] = (1, False)
        elif arg.n == pickletools.TAKEN_FROM_ARGUMENT4:
            counted[code] = (4, True)
        elif arg.n in (pickletools.TAKEN_FROM_ARGUMENT4U, pickletools.TAKEN_FROM_ARGUMENT8U):
            counted[code] = (4 if arg.n == pickletools.TAKEN_FROM_ARGUMENT4U else 8, False)
        elif arg.n == pickletools.UP_TO_NEWLINE:
            line.add(code)
    branches = [b"[" + b"".join(re.escape(bytes([c])) for c in codes) + b"]"
                + (b".{%d}" % n if n else b"") for n, codes in sorted(fixed.items())]
    # opcodes with a 1-byte count (short strings: most of a real file's opcodes after the
    # fixed-size ones), one branch per count; the loop still checks them where this fails
    short = [c for c, (k, _) in counted.items() if k == 1]
    branches.append(b"[" + b"".join(re.escape(bytes([c])) for c in short) + b"](?:"
                    + b"|".join(re.escape(bytes([k])) + (b".{%d}" % k if k else b"")
                                for k in range(256)) + b")")
    return re.compile(b"(?:" + b"|".join(branches) + b")*+", re.S), counted, frozenset(line)


_PUT, _LONG_BINPUT, _STOP, _FRAME = b"p"[0], b"r"[0], b"."[0], 0x95
_TWO_LINES = frozenset(b"ci")  # GLOBAL, INST: module and name lines
_SCANNED = frozenset((_PUT, _LONG_BINPUT, _STOP, _FRAME))
_RUN, _COUNTED, _LINE = _opcode_tables()


def _scan(data: bytes) -> None:
    """Refuse what the C unpickler would allocate before checking it against the data.

    A memo index (PUT / LONG_BINPUT) larger than the data makes it allocate and zero-fill a
    memo table of 16 bytes per index (a 9-byte pickle took 1 GB, up to 64 GB); a counted
    length (BINBYTES8, FRAME, ...) larger than the rest of the data is truncation. Runs of
    fixed-size opcodes are skipped by one regex match; the loop only visits counted opcodes,
    memo puts and line-terminated (protocol 0) opcodes. (Newer CPython releases fix the C
    unpickler itself, gh-115952; Python 3.11 does not.)
    """
    n = len(data)
    i = 2 if data[:1] == b"\x80" else 0
    match = _RUN.match
    while True:
        i = match(data, i).end()
        if i >= n:
            return
        code = data[i]
        i += 1
        counted = _COUNTED.get(code)
        if counted is not None or code == _FRAME:
            k, signed = counted or (8, False)
            size = int.from_bytes(data[i:i + k], "little", signed=signed)
            i += k
            if size > n - i:
                raise pickle.UnpicklingError(f"truncated pickle: an opcode at byte {i - k - 1} "
                                             f"claims {size} bytes, {max(n - i, 0)} remain")
            if size < 0:
                return  # the unpickler refuses it
            if code != _FRAME:  # a frame's opcodes are scanned in place
                i += size
        elif code == _LONG_BINPUT:
            index = int.from_bytes(data[i:i + 4], "little")
            if index > n:
                raise UnsafePickleError(f"memo index {index} beyond the {n}-byte pickle")
            i += 4
        elif code == _STOP:
            return
        else:  # line-terminated arguments (protocol 0), or an opcode the unpickler refuses
            end = data.find(b"\n", i)
            if end < 0 or code not in _LINE:
                return
            if code == _PUT and data[i:end].strip().isdigit() and int(data[i:end]) > n:
                raise UnsafePickleError(f"memo index {int(data[i:end])} beyond the {n}-byte pickle")
            if code in _TWO_LINES:
                end = data.find(b"\n", end + 1)
                if end < 0:
                    return
            i = end + 1


def safe_load(fh: BinaryIO, budget: int | None = None) -> Any:
    """Unpickle plain data from a binary file object; see module doc.

    The rest of the file is read into memory first. ``budget`` (bytes) defaults to
    :func:`allocation_budget` of the data's size.
    """
    return safe_loads(fh.read(), budget)


def safe_loads(data: bytes, budget: int | None = None) -> Any:
    """Unpickle plain data from bytes; see module doc."""
    limit = allocation_budget(len(data)) if budget is None else budget
    _scan(data)
    return _RestrictedUnpickler(io.BytesIO(data), limit).load()


def safe_load_path(path: str | os.PathLike) -> Any:
    """Unpickle plain data from the file at ``path``; see module doc."""
    with open_regular(path, expected="a pickle file") as fh:  # no FIFO, device or socket
        return safe_load(fh)
