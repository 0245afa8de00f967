"""Where magail_sumo writes: safe file names from data, atomic writes, owned output folders.

Three guarantees every command relies on (README, "Security and robustness"):

* **Names from data are file names, never paths.** :func:`safe_name` maps a scenario id (or any
  string from an input file) to a name of at most :data:`MAX_NAME` characters drawn from
  ``[A-Za-z0-9._-]`` that does not start with ``.``. An id that already is such a name maps to
  itself (every real WOMD id does), so existing outputs keep their names. Any other id maps to
  its safe characters (others become ``_``, leading dots dropped, cut to 48 characters) plus
  ``-`` and the first 12 hex digits of the SHA-256 of the id's UTF-8 bytes: distinct ids give
  distinct names, and :class:`NameRegistry` detects the (astronomically unlikely) collision. The
  original id is kept in the outputs' metadata. :func:`inside` checks a joined path stays in its
  folder.
* **Writes are atomic.** :func:`atomic_write` (and :func:`write_text` / :func:`write_bytes`)
  write a temporary file in the destination folder and ``os.replace`` it over the target, so a
  crash or a full disk leaves the old file or no file, never a half-written one.
* **Folders are owned.** :func:`claim_output_dir` marks a folder with :data:`MARKER` (JSON: the
  tools that wrote into it). A command writes only into a folder that is new, empty, or already
  marked as magail_sumo's; it refuses a non-empty folder it did not create.
  :func:`remove_owned` deletes only the files a tool listed as its own, and the folder itself
  only when nothing else is left in it.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import tempfile
from os import PathLike
from pathlib import Path
from typing import Iterable, Iterator

from magail_sumo.errors import MagailSumoError

#: longest name :func:`safe_name` returns (well inside every file system's 255-byte limit,
#: leaving room for suffixes such as ``.net.xml``)
MAX_NAME = 100
_SAFE = re.compile(r"[A-Za-z0-9._-]+")
_UNSAFE_CHAR = re.compile(r"[^A-Za-z0-9._-]")
#: file marking a folder as written by magail_sumo
MARKER = ".magail_sumo.json"


class OutputError(MagailSumoError):
    """An output path is unsafe or not ours to write."""


def finite_json(v: object) -> object:
    """``v`` with every non-finite float (NaN, inf) in nested dicts / lists / tuples replaced by
    None, so ``json.dumps(..., allow_nan=False)`` writes it (``null``)."""
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: finite_json(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [finite_json(x) for x in v]
    return v


def printable(text: str, limit: int = 120) -> str:
    """``text`` for a one-line message: control characters escaped, cut to ``limit``."""
    out = text.encode("unicode_escape", "backslashreplace").decode("ascii")
    return out if len(out) <= limit else out[:limit - 3] + "..."


def one_line(text: object, limit: int = 300) -> str:
    """``str(text)`` (e.g. an exception) for a one-line message: whitespace runs collapsed,
    control characters escaped, cut to ``limit`` (see :func:`printable`)."""
    return printable(" ".join(str(text).split()), limit)


def _digest(name: str) -> str:
    return hashlib.sha256(name.encode("utf-8", "surrogatepass")).hexdigest()[:12]


def is_safe_name(name: str) -> bool:
    """True when ``name`` is used unchanged by :func:`safe_name`."""
    return (0 < len(name) <= MAX_NAME and _SAFE.fullmatch(name) is not None
            and not name.startswith("."))


def safe_name(name: str) -> str:
    """A file name for ``name`` (see the module doc for the mapping)."""
    if is_safe_name(name):
        return name
    stem = _UNSAFE_CHAR.sub("_", name).lstrip(".")[:48]
    return f"{stem or '_'}-{_digest(name)}"


class NameRegistry:
    """Safe names handed out within one output folder; a collision is an error, not an overwrite."""

    def __init__(self) -> None:
        self._owner: dict[str, str] = {}

    def name(self, original: str) -> str:
        """:func:`safe_name` of ``original``; :class:`OutputError` if another id already has it."""
        name = safe_name(original)
        prev = self._owner.setdefault(name, original)
        if prev != original:
            raise OutputError(f"scenario ids {printable(prev)!r} and {printable(original)!r} "
                              f"map to the same file name {name!r}")
        return name


def inside(folder: str | PathLike, *parts: str) -> Path:
    """``folder / parts...``, refused unless it resolves inside ``folder``."""
    base = Path(folder)
    path = base.joinpath(*parts)
    root = os.path.realpath(base)
    real = os.path.realpath(path)
    if os.path.commonpath([root, real]) != root or real == root:
        raise OutputError(f"{printable(str(path))}: would be written outside {base}")
    return path


def _file_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


@contextlib.contextmanager
def atomic_write(path: str | PathLike, mode: str = "wb") -> Iterator:
    """Open a temporary file beside ``path`` for writing; on success it replaces ``path``.

    On any exception (a full disk included) the temporary file is removed and ``path`` is left
    as it was.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name[:60]}.", suffix=".tmp", dir=path.parent)
    os.fchmod(fd, _file_mode())  # mkstemp's 0600 -> what open() would give (umask)
    try:
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_path(path: str | PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` for a writer that takes a file name (Parquet, torch,
    matplotlib, an external tool); moved over ``path`` when the block succeeds."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name[:60]}.", suffix=".tmp", dir=path.parent)
    os.fchmod(fd, _file_mode())  # mkstemp's 0600 -> what open() would give (umask)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def write_text(path: str | PathLike, text: str) -> Path:
    """Atomically write ``text`` (UTF-8) to ``path``."""
    with atomic_write(path, "w") as fh:
        fh.write(text)
    return Path(path)


def write_bytes(path: str | PathLike, data: bytes) -> Path:
    """Atomically write ``data`` to ``path``."""
    with atomic_write(path, "wb") as fh:
        fh.write(data)
    return Path(path)


def read_marker(folder: str | PathLike) -> dict | None:
    """The folder's :data:`MARKER` content, or None when it has none (or an unreadable one)."""
    try:
        data = json.loads((Path(folder) / MARKER).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and isinstance(data.get("tools"), dict) else None


def claim_output_dir(folder: str | PathLike, tool: str, owned: Iterable[str] = ()) -> Path:
    """Make ``folder`` an output folder of ``tool``; :class:`OutputError` when it is not ours.

    The folder may be new, empty, or already marked by any magail_sumo tool (a networks folder
    is shared by ``convert``, ``expert`` and ``evaluate``). ``owned`` lists the top-level names
    ``tool`` writes there (recorded for :func:`remove_owned`).
    """
    d = Path(folder)
    if d.exists() and not d.is_dir():
        raise OutputError(f"{d}: exists and is not a folder")
    marker = read_marker(d) if d.is_dir() else None
    if marker is None and d.is_dir() and any(d.iterdir()):
        raise OutputError(f"{d}: folder is not empty and was not written by magail_sumo "
                          "(choose a new or empty folder)")
    d.mkdir(parents=True, exist_ok=True)
    marker = marker or {"tools": {}}
    names = set(marker["tools"].get(tool, ())) | set(owned)
    if tool not in marker["tools"] or names != set(marker["tools"][tool]):
        marker["tools"][tool] = sorted(names)
        write_text(d / MARKER, json.dumps(marker, indent=1))
    return d


def remove_owned(folder: str | PathLike, tool: str) -> None:
    """Delete what ``tool`` recorded as its own in ``folder`` (and the folder, once empty).

    :class:`OutputError` when the folder holds no marker of ``tool``: nothing is deleted then.
    """
    import shutil

    d = Path(folder)
    if not d.exists():
        return
    marker = read_marker(d)
    if marker is None or tool not in marker["tools"]:
        raise OutputError(f"{d}: not a folder written by magail-sumo {tool}; nothing removed")
    for name in marker["tools"].pop(tool):
        target = d / name
        if target.parent != d or name in ("", ".", "..", MARKER):
            continue
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        elif target.exists() or target.is_symlink():
            target.unlink()
    if marker["tools"]:
        write_text(d / MARKER, json.dumps(marker, indent=1))
        return
    (d / MARKER).unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        d.rmdir()  # only when nothing else is left
