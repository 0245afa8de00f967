"""Reading input files safely: regular files only, never blocking, bounded sizes and nesting.

Every file the tool reads on a user's behalf (scene files, bundles' ``conversion.json``, SUMO
configs and the files they name, submissions, figures, markers) is opened here:

* **Regular files only.** ``open`` on a FIFO blocks until a writer appears and a device
  (``/dev/zero``) streams without end; both are refused before a byte is read, also when reached
  through a symbolic link. The file is opened non-blocking and checked with ``fstat`` on the
  open descriptor, so a path swapped for a FIFO after the check still cannot block.
* **Bounded size.** :func:`read_bytes` / :func:`read_text` / :func:`read_json` take a cap in
  bytes proportional to what the file is (a marker: 1 MiB; a bundle's report: 64 MiB); a larger
  file is refused by its size, and a file that grows while read is cut at the cap and refused.
* **Bounded nesting.** :func:`read_json` refuses documents nested deeper than ``max_depth``
  (default 64), so no later recursive walk of the value can overflow the stack.

Errors are :class:`InputFileError`: one line, ``"<path>: <problem>"``; :attr:`~InputFileError.problem`
holds the phrase alone for callers that add a record number (:mod:`converters.files`).
"""

from __future__ import annotations

import errno
import json
import os
import stat
from os import PathLike
from pathlib import Path
from typing import BinaryIO

from magail_sumo.errors import MagailSumoError

KiB, MiB, GiB = 1 << 10, 1 << 20, 1 << 30
#: default cap of :func:`read_json`: metadata (``conversion.json``, manifests, run records)
JSON_LIMIT = 64 * MiB
#: default nesting bound of :func:`read_json`
JSON_DEPTH = 64

_KINDS = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


class InputFileError(MagailSumoError):
    """An input file cannot be read safely: ``"<path>: <problem>"``.

    :param path: the file as the user (or the file naming it) gave it.
    :param problem: the short phrase alone ("is a FIFO (named pipe), expected a regular file").
    """

    def __init__(self, path: str | PathLike, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


def path_problem(path: str | PathLike) -> tuple[str, os.stat_result | None]:
    """``("", stat)`` for an existing regular file or directory (links followed), else
    ``(problem, None)`` with a short phrase: ``"no such file"``, ``"symlink loop (too many
    levels of symbolic links)"``, ``"is a FIFO (named pipe), expected a regular file"``, ..."""
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


def regular_file(path: str | PathLike, expected: str = "a file") -> os.stat_result:
    """The ``stat`` of ``path`` when it is an existing regular file (links followed);
    :class:`InputFileError` otherwise (a directory: "is a directory, expected ``expected``")."""
    problem, st = path_problem(path)
    if problem:
        raise InputFileError(path, problem)
    if stat.S_ISDIR(st.st_mode):  # type: ignore[union-attr]
        raise InputFileError(path, f"is a directory, expected {expected}")
    return st  # type: ignore[return-value]


def open_regular(path: str | PathLike, buffering: int = -1,
                 expected: str = "a file") -> BinaryIO:
    """Open a regular file for binary reading; :class:`InputFileError` for anything else
    (module doc: non-blocking open, ``fstat`` of the descriptor, then blocking reads)."""
    p = Path(path)
    regular_file(p, expected)
    try:
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        what = ("symlink loop (too many levels of symbolic links)" if exc.errno == errno.ELOOP
                else f"cannot read ({exc.strerror or exc})")
        raise InputFileError(p, what) from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise InputFileError(p, "is not a regular file")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb", buffering=buffering)
    except BaseException:
        os.close(fd)
        raise


def _size(n: int) -> str:
    for unit, scale in (("GiB", GiB), ("MiB", MiB), ("KiB", KiB)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n} bytes"


def read_bytes(path: str | PathLike, limit: int, expected: str = "a file") -> bytes:
    """The content of regular file ``path``, at most ``limit`` bytes; a larger file (by its
    size, or by what it yields while read) is refused with both sizes named."""
    with open_regular(path, expected=expected) as fh:
        size = os.fstat(fh.fileno()).st_size
        if size > limit:
            raise InputFileError(path, f"is {_size(size)}, more than the {_size(limit)} "
                                       f"expected of {expected}")
        try:  # read(n) allocates n bytes up front: the file's size, not the cap
            data = fh.read(min(limit, size) + 1)
        except OSError as exc:
            raise InputFileError(path, f"cannot read ({exc.strerror or exc})") from None
    if len(data) > limit:
        raise InputFileError(path, f"holds more than the {_size(limit)} expected of {expected}")
    return data


def read_text(path: str | PathLike, limit: int, expected: str = "a text file") -> str:
    """:func:`read_bytes` decoded as UTF-8 (refused, naming the byte offset, when it is not)."""
    data = read_bytes(path, limit, expected)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputFileError(path, f"not UTF-8 text (byte {exc.start})") from None


def json_depth_exceeds(value: object, max_depth: int) -> bool:
    """Whether ``value`` (lists and dicts) nests deeper than ``max_depth``; iterative."""
    stack = [(value, 1)]
    while stack:
        v, depth = stack.pop()
        if isinstance(v, (list, dict)):
            if depth > max_depth:
                return True
            stack.extend((c, depth + 1) for c in (v.values() if isinstance(v, dict) else v))
    return False


def parse_json(text: str | bytes, source: str | PathLike, max_depth: int = JSON_DEPTH) -> object:
    """``text`` as JSON; :class:`InputFileError` naming ``source`` when it is not JSON or nests
    deeper than ``max_depth`` (also when deeper than Python's parser can go)."""
    try:
        value = json.loads(text)
    except RecursionError:
        raise InputFileError(source, f"JSON nested deeper than {max_depth} levels") from None
    except ValueError as exc:
        raise InputFileError(source, f"not valid JSON ({exc})") from None
    if json_depth_exceeds(value, max_depth):
        raise InputFileError(source, f"JSON nested deeper than {max_depth} levels")
    return value


def read_json(path: str | PathLike, limit: int = JSON_LIMIT, max_depth: int = JSON_DEPTH,
              expected: str = "a JSON file") -> object:
    """The JSON value of regular file ``path`` (at most ``limit`` bytes, nesting at most
    ``max_depth``); :class:`InputFileError` otherwise."""
    return parse_json(read_bytes(path, limit, expected), path, max_depth)
