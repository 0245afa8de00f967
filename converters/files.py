"""Opening recorded-scene files safely: :mod:`magail_sumo.inputs`' guard, errors as
:class:`~magail_sumo.errors.SceneFormatError` (file, record, problem).

``open`` on a FIFO blocks until a writer appears (``inspect`` on a named pipe hung forever) and a
device can stream without end; such paths are refused before they are read. A symlink loop is
reported as such (``ELOOP``), not as a missing file.
"""

from __future__ import annotations

from os import PathLike
from pathlib import Path
from typing import BinaryIO

from magail_sumo.errors import SceneFormatError
from magail_sumo.inputs import InputFileError, path_problem
from magail_sumo.inputs import open_regular as _open_regular

__all__ = ["open_regular", "path_problem"]


def open_regular(path: str | PathLike, record: int | None = None,
                 buffering: int = -1, expected: str = "a file") -> BinaryIO:
    """Open a regular file for binary reading (:func:`magail_sumo.inputs.open_regular`: never
    blocks on a FIFO or streams a device); :class:`SceneFormatError` naming ``record`` for
    anything else (a directory: "is a directory, expected ``expected``")."""
    try:
        return _open_regular(Path(path), buffering, expected)
    except InputFileError as exc:
        raise SceneFormatError(path, record, exc.problem) from None
