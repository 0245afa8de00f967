"""Where magail_sumo writes: safe file names from data, writes kept inside their output folder,
atomic writes, owned output folders.

Four guarantees every command relies on (README, "Security and robustness"):

* **Names from data are file names, never paths.** :func:`safe_name` maps a scenario id (or any
  string from an input file) to a name of at most :data:`MAX_NAME` characters drawn from
  ``[A-Za-z0-9._-]`` that does not start with ``.``. An id that already is such a name maps to
  itself (every real WOMD id does), so existing outputs keep their names, unless it could be
  taken for a file or folder the tool writes beside it (``summary.csv``, ``report``: see
  :data:`TOOL_SUFFIXES`, :data:`TOOL_FOLDERS`). Any other id maps to
  its safe characters (others become ``_``, leading dots dropped, cut to 48 characters) plus
  ``-`` and the first 12 hex digits of the SHA-256 of the id's UTF-8 bytes: distinct ids give
  distinct names, and :class:`NameRegistry` detects the (astronomically unlikely) collision. The
  original id is kept in the outputs' metadata.
* **Writes stay in their output folder.** Every path a command derives inside an output folder
  (a file, a sub-folder, a file appended to) goes through :func:`inside` (or
  :func:`inside_dir`, which also makes the sub-folder): the path with every symbolic link
  resolved must lie inside the folder, so a link planted in an output folder (``DIR/report``,
  ``RUN/checkpoints``, ``RUN/skipped_scenes.tsv``, a dangling one included) is refused with one
  :class:`OutputError` line naming it instead of being written through (the output folder
  itself, named by the user, may be a link).
* **Writes are atomic.** :func:`atomic_write` (and :func:`write_text` / :func:`write_bytes`)
  write a temporary file in the destination folder and ``os.replace`` it over the target, so a
  crash or a full disk leaves the old file or no file, never a half-written one; the
  ``OSError`` of a failed write names the target (not the temporary file), and a target that
  is a folder is refused before anything is written. :func:`atomic_paths` writes several files
  as a group: none is replaced before all of them are written.
* **Folders are owned.** :func:`claim_output_dir` marks a folder with :data:`MARKER` (JSON: the
  tools that wrote into it). A command writes only into a folder that is new, empty, or already
  marked as magail_sumo's; it refuses a non-empty folder it did not create.
  :func:`remove_owned` deletes only the files a tool listed as its own, and the folder itself
  only when nothing else is left in it. A marker that is not valid (not JSON, nested too deep,
  not ``{"tools": {TOOL: [NAME, ...]}}`` with string names) is an :class:`OutputError` naming
  the marker file: such a folder is neither written into nor cleared.
"""

from __future__ import annotations

import contextlib
import errno
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
from magail_sumo.inputs import InputFileError, open_regular

#: longest name :func:`safe_name` returns (well inside every file system's 255-byte limit,
#: leaving room for suffixes such as ``.net.xml``)
MAX_NAME = 100
_SAFE = re.compile(r"[A-Za-z0-9._-]+")
_UNSAFE_CHAR = re.compile(r"[^A-Za-z0-9._-]")
#: file marking a folder as written by magail_sumo
MARKER = ".magail_sumo.json"
#: largest marker file read (bytes)
MAX_MARKER_BYTES = 64 << 20


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


#: name endings of files the commands write beside the ones named after data (a scenario id
#: ending so, e.g. ``summary.csv``, would take the place of the tool's own file)
TOOL_SUFFIXES = (".csv", ".json", ".yaml", ".yml", ".md", ".tsv", ".html", ".txt", ".log")
#: folders the commands make beside the ones named after data
TOOL_FOLDERS = frozenset({"report", "city", "rollouts", "fcd", "scenes", "networks", "img",
                          "checkpoints", "tb", "expert", "eval", "train", "seed0"})


def safe_name(name: str) -> str:
    """A file name for ``name`` (see the module doc for the mapping): ``name`` itself when it
    is safe and cannot be taken for a file or folder the tool writes beside it
    (:data:`TOOL_SUFFIXES`, :data:`TOOL_FOLDERS`), else its safe characters plus a digest."""
    low = name.lower()
    if is_safe_name(name) and not low.endswith(TOOL_SUFFIXES) and low not in TOOL_FOLDERS:
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
    """``folder / parts...`` (returned unresolved), refused with a one-line :class:`OutputError`
    naming it unless it lies inside ``folder`` once every symbolic link in it is resolved (a
    dangling link by where it points; a link that stays inside the folder is accepted) and is
    not ``folder`` itself. Nothing is created. Every write into an output folder goes through
    this check (or :func:`inside_dir`); ``folder`` itself may be a link (the user named it)."""
    base = Path(folder)
    path = base.joinpath(*parts)
    root = os.path.realpath(base)
    real = os.path.realpath(path)
    if os.path.commonpath([root, real]) != root or real == root:
        raise OutputError(f"{printable(str(path))}: would be written outside "
                          f"{printable(str(base))} (it resolves to {printable(real)}: a symbolic "
                          "link or '..' leads out of the output folder)")
    return path


def inside_dir(folder: str | PathLike, *parts: str) -> Path:
    """:func:`inside` ``(folder, *parts)``, made a folder (with its parents) when missing: the
    sub-folder a command writes into. :class:`OutputError` (one line naming it) when it leads
    out of ``folder`` or exists and is not a folder (a file, a dangling link)."""
    path = inside(folder, *parts)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputError(f"{printable(str(path))}: exists and is not a folder") from None
    return path


def _file_mode() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def _not_a_folder(path: Path) -> None:
    if path.is_dir():
        raise OutputError(f"{printable(str(path))}: is a folder (give a file name)")


def _renamed(exc: OSError, path: Path) -> OSError:
    """An ``OSError`` of ``exc``'s errno (and subclass) and reason naming ``path``."""
    return OSError(exc.errno, exc.strerror or type(exc).__name__, str(path))


def _naming(exc: OSError, path: Path, tmps: dict[str, Path]) -> OSError:
    """``exc`` naming the file being written: :func:`_renamed` to the target of the temporary
    file it names (``tmps``: temporary -> target), to ``path`` when it names no file; ``exc``
    itself when it names another file (one the writer was reading, say)."""
    name = exc.filename
    if name is None:
        return _renamed(exc, path)
    return _renamed(exc, tmps[str(name)]) if str(name) in tmps else exc


def _mkstemp(path: Path) -> tuple[int, str]:
    """A temporary file beside ``path`` (mode as ``open`` would give it); an ``OSError``
    names ``path``."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name[:60]}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise _renamed(exc, path) from exc
    try:
        os.fchmod(fd, _file_mode())  # mkstemp's 0600 -> what open() would give (umask)
    except BaseException:
        os.close(fd)
        os.unlink(tmp)
        raise
    return fd, tmp


@contextlib.contextmanager
def atomic_write(path: str | PathLike, mode: str = "wb") -> Iterator:
    """Open a temporary file beside ``path`` for writing; on success it replaces ``path``.

    On any exception (a full disk included) the temporary file is removed and ``path`` is left
    as it was; an ``OSError`` naming the temporary file or no file (creating, writing, syncing
    or renaming it) is raised again as an ``OSError`` of the same errno whose ``filename`` is
    ``path`` (one naming another file, read in the block, is left as it is).
    :class:`OutputError` before anything is written when ``path`` is a folder.
    """
    path = Path(path)
    _not_a_folder(path)
    fd, tmp = _mkstemp(path)
    try:
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            new = _naming(exc, path, {tmp: path})
            if new is not exc:
                raise new from exc
        raise


@contextlib.contextmanager
def atomic_path(path: str | PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` for a writer that takes a file name (Parquet, torch,
    matplotlib, an external tool); moved over ``path`` when the block succeeds. Failures as
    :func:`atomic_write` (the temporary file removed; an ``OSError`` names ``path``)."""
    with atomic_paths(path) as (tmp,):
        yield tmp


@contextlib.contextmanager
def atomic_paths(*paths: str | PathLike) -> Iterator[list[Path]]:
    """Temporary paths beside each of ``paths``, for files that belong together (a checkpoint
    and the card holding its checksum): when the block succeeds each is synced and moved over
    its path, in order, so no file is replaced before every one is written. On any exception
    every temporary file is removed and the ``paths`` are left as they were; an ``OSError``
    naming a temporary file, or no file, is raised again naming the path being written (the
    temporary file's target; else, in the block, the first path; after it, the one being
    synced or moved). :class:`OutputError` before anything is written when one is a folder."""
    targets = [Path(p) for p in paths]
    for p in targets:
        _not_a_folder(p)
    tmps: list[Path] = []
    current = targets[0]
    try:
        for p in targets:
            fd, tmp = _mkstemp(p)
            os.close(fd)
            tmps.append(Path(tmp))
        yield list(tmps)
        for p, tmp in zip(targets, tmps):
            current = p
            fd = os.open(tmp, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        for p, tmp in zip(targets, tmps):
            current = p
            os.replace(tmp, p)
    except BaseException as exc:
        for tmp in tmps:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        if isinstance(exc, OSError):
            new = _naming(exc, current, {str(t): p for t, p in zip(tmps, targets)})
            if new is not exc:
                raise new from exc
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


#: errnos of a write that failed for want of room (a full disk, a quota, a file-size
#: limit) or on a read-only file system
_WRITE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS)


def os_error(exc: OSError, fallback: str | PathLike) -> OutputError:
    """One :class:`OutputError` line for ``exc``: ``FILE: cannot write (REASON)`` for a full
    disk, an exhausted quota, a file-size limit or a read-only file system, else ``FILE:
    REASON``; FILE is the file ``exc`` names (the target of an atomic write, see
    :func:`atomic_write`), else ``fallback``."""
    name = printable(str(exc.filename if exc.filename is not None else fallback), 300)
    why = exc.strerror or one_line(exc, 200) or type(exc).__name__
    if exc.errno in _WRITE_ERRNOS:
        return OutputError(f"{name}: cannot write ({why})")
    return OutputError(f"{name}: {why}")


def check_writable_file(path: str | PathLike, hint: str) -> Path:
    """``path`` as a file a command will write later, checked before its slow work: a
    one-line :class:`OutputError` naming it when it is a folder (``PATH: is a folder (HINT)``),
    when one of its parents is not a folder, or when its folder cannot be made or written
    into (a temporary file is created there and removed). Its folder is made when missing."""
    out = Path(path)
    if out.is_dir():
        raise OutputError(f"{printable(str(out))}: is a folder ({hint})")
    blocker = next((p for p in out.absolute().parents if p.exists()), None)
    if blocker is not None and not blocker.is_dir():
        raise OutputError(f"{printable(str(out))}: cannot be written "
                          f"({printable(str(blocker))} is not a folder)")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=out.parent):
            pass
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
        raise OutputError(f"{printable(str(out))}: cannot be written ({why})") from None
    return out


def read_marker(folder: str | PathLike) -> dict | None:
    """The folder's :data:`MARKER`, ``{"tools": {TOOL: [NAME, ...]}, ...}``: None when the folder
    holds no marker file; :class:`OutputError` (one line naming the marker file and the
    problem) when it holds one that is not a valid marker: unreadable, larger than
    :data:`MAX_MARKER_BYTES`, not UTF-8 JSON, nested too deep to parse, or not an object whose
    ``tools`` maps each tool to a list of file names (strings)."""
    path = Path(folder) / MARKER
    if not os.path.lexists(path):
        return None

    def invalid(why: str) -> OutputError:
        return OutputError(f"{printable(str(path))}: not a valid magail_sumo marker ({why})")

    try:  # a regular file only: a FIFO would block, a device stream
        with open_regular(path, expected="a marker file") as fh:
            raw = fh.read(MAX_MARKER_BYTES + 1)
    except InputFileError as exc:
        raise invalid(exc.problem) from None
    except OSError as exc:
        raise invalid(f"cannot read it: {exc.strerror or type(exc).__name__}") from None
    if len(raw) > MAX_MARKER_BYTES:
        raise invalid(f"larger than {MAX_MARKER_BYTES} bytes")
    try:
        data = json.loads(raw.decode("utf-8"))
    except RecursionError:
        raise invalid("nested too deep") from None
    except ValueError as exc:  # UnicodeDecodeError included
        raise invalid(f"not JSON: {one_line(exc, 100)}") from None
    tools = data.get("tools") if isinstance(data, dict) else None
    if not isinstance(tools, dict) or not all(
            isinstance(names, list) and all(isinstance(n, str) for n in names)
            for names in tools.values()):
        raise invalid('expected {"tools": {"TOOL": ["NAME", ...]}}')
    return data


#: name of the temporary file an atomic write of the marker makes (:func:`_mkstemp`)
_MARKER_TMP = re.compile(r"^\." + re.escape(MARKER) + r"\.[A-Za-z0-9_]+\.tmp$")


def _ours_unfinished(path: Path) -> bool:
    """A marker's temporary file a killed command left (``..magail_sumo.json.XXXX.tmp``, a
    regular file): a folder holding only such files counts as empty. It is left alone, never
    read or removed."""
    return bool(_MARKER_TMP.match(path.name)) and path.is_file() and not path.is_symlink()


def claim_output_dir(folder: str | PathLike, tool: str, owned: Iterable[str] = ()) -> Path:
    """Make ``folder`` an output folder of ``tool``; :class:`OutputError` when it is not ours.

    The folder may be new, empty (but for marker temporary files a killed command left), or
    already marked by any magail_sumo tool (a networks folder is shared by ``convert``,
    ``expert`` and ``evaluate``). ``owned`` lists the top-level names
    ``tool`` writes there (recorded for :func:`remove_owned`). A folder whose marker is not
    valid (:func:`read_marker`) is refused, naming the marker file; nothing is written then.
    """
    d = Path(folder)
    if d.exists() and not d.is_dir():
        raise OutputError(f"{d}: exists and is not a folder")
    marker = read_marker(d) if d.is_dir() else None
    if marker is None and d.is_dir() and any(not _ours_unfinished(p) for p in d.iterdir()):
        raise OutputError(f"{d}: folder is not empty and was not written by magail_sumo "
                          "(choose a new or empty folder)")
    d.mkdir(parents=True, exist_ok=True)
    marker = marker or {"tools": {}}
    names = set(marker["tools"].get(tool, ())) | set(owned)
    if tool not in marker["tools"] or names != set(marker["tools"][tool]):
        marker["tools"][tool] = sorted(names)
        write_text(inside(d, MARKER), json.dumps(marker, indent=1))
    return d


def remove_owned(folder: str | PathLike, tool: str) -> None:
    """Delete what ``tool`` recorded as its own in ``folder`` (and the folder, once empty).

    :class:`OutputError` when the folder holds no marker of ``tool`` or a marker that is not
    valid (:func:`read_marker`; the message names the marker file): nothing is deleted then.
    """
    import shutil

    d = Path(folder)
    if not d.exists():
        return
    try:
        marker = read_marker(d)
    except OutputError as exc:
        raise OutputError(f"{exc}; nothing removed") from None
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
        write_text(inside(d, MARKER), json.dumps(marker, indent=1))
        return
    (d / MARKER).unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        d.rmdir()  # only when nothing else is left
