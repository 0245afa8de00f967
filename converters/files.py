"""Opening input files safely: only regular files, never blocking, one-line errors.

``open`` on a FIFO blocks until a writer appears (``inspect`` on a named pipe hung forever) and a
device can stream without end; such paths are refused before they are read. A symlink loop is
reported as such (``ELOOP``), not as a missing file.
"""

from __future__ import annotations

import errno
import os
import stat
from os import PathLike
from pathlib import Path
from typing import BinaryIO

from magail_sumo.errors import SceneFormatError

_KINDS = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def path_problem(path: str | PathLike) -> tuple[str, os.stat_result | None]:
    """``("", stat)`` for an existing regular file or directory, else ``(problem, None)``.

    The problem is a short phrase for a :class:`SceneFormatError`: ``"no such file"``,
    ``"symlink loop (too many levels of symbolic links)"``, ``"is a FIFO (named pipe), expected
    a regular file"``, ...
    """
    p = Path(path)
    try:
        st = os.stat(p)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "symlink loop (too many levels of symbolic links)", None
        if exc.errno == errno.ENOENT:
            return ("broken symbolic link (its target does not exist)" if os.path.islink(p)
                    else "no such file"), None
        if exc.errno == errno.ENOTDIR:
            return "no such file (a parent is not a folder)", None
        return f"cannot read ({exc.strerror or exc})", None
    except ValueError:  # embedded NUL byte in the name
        return "invalid file name", None
    for test, kind in _KINDS:
        if test(st.st_mode):
            return f"is {kind}, expected a regular file", None
    return "", st


def open_regular(path: str | PathLike, record: int | None = None,
                 buffering: int = -1, expected: str = "a file") -> BinaryIO:
    """Open a regular file for binary reading; :class:`SceneFormatError` for anything else
    (a directory: "is a directory, expected ``expected``").

    Opened non-blocking and checked with ``fstat`` (a path swapped for a FIFO after the check
    still cannot block), then switched back to blocking reads.
    """
    p = Path(path)
    problem, st = path_problem(p)
    if problem:
        raise SceneFormatError(p, record, problem)
    if stat.S_ISDIR(st.st_mode):  # type: ignore[union-attr]
        raise SceneFormatError(p, record, f"is a directory, expected {expected}")
    try:
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        what = ("symlink loop (too many levels of symbolic links)" if exc.errno == errno.ELOOP
                else f"cannot read ({exc.strerror or exc})")
        raise SceneFormatError(p, record, what) from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise SceneFormatError(p, record, "is not a regular file")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb", buffering=buffering)
    except BaseException:
        os.close(fd)
        raise
