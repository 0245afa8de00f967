"""A restricted unpickler: loads plain data (builtins containers, numpy arrays) and nothing else.

Loading a pickle can run arbitrary code through the globals it names. This unpickler resolves
only an allowlist of data types; any other global (``os.system``, a user class, even
``numpy.load``) is refused with :class:`UnsafePickleError` before anything is called.
"""

from __future__ import annotations

import _compat_pickle
import builtins
import codecs
import collections
import io
import pickle
from typing import Any, BinaryIO

import numpy as np

_NUMPY_CORE = getattr(np, "_core", None) or np.core  # numpy 2 vs 1

#: (module, name) -> object. Numpy pickles name their internals under ``numpy.core`` (numpy 1)
#: or ``numpy._core`` (numpy 2); both spellings are accepted.
_ALLOWED: dict[tuple[str, str], Any] = {}
for _mod in ("numpy.core", "numpy._core"):
    _ALLOWED[(f"{_mod}.multiarray", "_reconstruct")] = _NUMPY_CORE.multiarray._reconstruct
    _ALLOWED[(f"{_mod}.multiarray", "scalar")] = _NUMPY_CORE.multiarray.scalar
    _ALLOWED[(f"{_mod}.numeric", "_frombuffer")] = _NUMPY_CORE.numeric._frombuffer
_ALLOWED[("numpy", "ndarray")] = np.ndarray
_ALLOWED[("numpy", "dtype")] = np.dtype
for _name in ("int", "float", "complex", "bool", "str", "bytes", "bytearray", "tuple", "list",
              "dict", "set", "frozenset", "slice", "range"):
    _ALLOWED[("builtins", _name)] = getattr(builtins, _name)
# Real ScenarioNet files hold ``number_summary.num_moving_objects_each_type`` as a
# ``defaultdict(int)``: a plain data container, allowed together with OrderedDict.
_ALLOWED[("collections", "defaultdict")] = collections.defaultdict
_ALLOWED[("collections", "OrderedDict")] = collections.OrderedDict
# Protocol <= 2 pickles spell bytes as ``_codecs.encode(str, "latin1")``: a pure function.
_ALLOWED[("_codecs", "encode")] = codecs.encode
# numpy's own scalar dtype classes (numpy.dtypes.Float32DType, ...) appear in numpy>=2 pickles.
for _name in dir(getattr(np, "dtypes", object())):
    if _name.endswith("DType"):
        _ALLOWED[("numpy.dtypes", _name)] = getattr(np.dtypes, _name)


class UnsafePickleError(pickle.UnpicklingError):
    """The pickle names a global outside the allowlist; nothing was executed."""


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        # Python 2 spellings of protocol <= 2 pickles (__builtin__.long, ...), mapped as pickle does
        if (module, name) in _compat_pickle.NAME_MAPPING:
            module, name = _compat_pickle.NAME_MAPPING[(module, name)]
        elif module in _compat_pickle.IMPORT_MAPPING:
            module = _compat_pickle.IMPORT_MAPPING[module]
        try:
            return _ALLOWED[(module, name)]
        except KeyError:
            raise UnsafePickleError(
                f"refused to load {module}.{name}: only numpy arrays and builtin containers are allowed"
            ) from None

    def persistent_load(self, pid: Any) -> Any:
        raise UnsafePickleError("refused persistent id in pickle")


def safe_load(fh: BinaryIO) -> Any:
    """Unpickle plain data from a binary file object; see module doc."""
    return _RestrictedUnpickler(fh).load()


def safe_loads(data: bytes) -> Any:
    """Unpickle plain data from bytes; see module doc."""
    return safe_load(io.BytesIO(data))
