"""Run configuration as data: typed dataclasses loaded from YAML with strict checking.

Every key of a YAML file must name a field of the target dataclass (nested dataclasses for
nested mappings) and every value must have the field's type; anything else is refused with a
:class:`ConfigError` naming the file, the key path and the problem. Nothing is guessed or
silently ignored. Numbers must be finite (no ``.nan`` / ``.inf``); value ranges are checked by
the dataclasses' ``__post_init__`` (raising :class:`FieldError`, reported with the dotted key).
The YAML must be UTF-8 text of at most :data:`MAX_CONFIG_BYTES`, with no duplicate keys and no
aliases (``*name``: a few hundred bytes of nested aliases expand to gigabytes). Error messages
are one line of bounded length.

Composition. A file may start from others: ``extends: FILE`` or ``extends: [FILE, ...]``
(paths relative to the file that names them). The bases are resolved first, in order, each
with its own ``extends``, and merged: mappings key by key, any other value (a list included)
replaced whole by the later one; the file's own settings go on top. Each extended file is read
with every check above; unknown keys are refused naming the file that holds them; a cycle, a
chain deeper than :data:`MAX_EXTENDS_DEPTH` or more than :data:`MAX_EXTENDS_FILES` files are
refused naming the file. Overrides (``magail-sumo train --set KEY=VALUE``,
:func:`parse_override`) are one more layer on top: ``KEY`` a dotted key, ``VALUE`` read as
YAML by the same strict loader, then checked like a file's setting. A config dataclass may
rewrite its mapping in each layer before the layers are merged, by a classmethod
``expand_config(data, base) -> data`` (``base``: the folder of the file of the layer, the
working directory for the overrides, which form one layer), naming the keys it consumes in
a class attribute ``EXPAND_KEYS`` — :class:`~magail_sumo.training.config.ScenesConfig`
turns ``split`` / ``part`` into ``files`` this way. The result is a plain config: ``extends`` is
gone, so :func:`record_run` records exactly the settings a run used.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
import re
import subprocess
import sys
import types
import typing
from os import PathLike
from pathlib import Path
from typing import Any, Iterable, TypeVar

import yaml

from magail_sumo.errors import MagailSumoError
from magail_sumo.outputs import write_text

T = TypeVar("T")


#: largest config file read (bytes)
MAX_CONFIG_BYTES = 1 << 20
#: longest :class:`ConfigError` message :func:`load_config` gives (characters)
MAX_MESSAGE = 400
#: longest chain of ``extends`` (a file extending a file extending ...), the first file included
MAX_EXTENDS_DEPTH = 16
#: most distinct files one config may be composed of
MAX_EXTENDS_FILES = 64
#: longest ``--set KEY=VALUE`` token (characters)
MAX_OVERRIDE = 10_000


class ConfigError(MagailSumoError):
    """A configuration file or value is invalid."""


class FieldError(ValueError):
    """A config value out of range, raised by a config dataclass's ``__post_init__``;
    :func:`from_dict` reports it as a :class:`ConfigError` naming the dotted key.

    :param key: the field (dotted for a field of a nested config, e.g. ``limits.max_accel``).
    :param problem: what is wrong (e.g. ``must be >= 1, got 0``).
    """

    def __init__(self, key: str, problem: str) -> None:
        self.key, self.problem = key, problem
        super().__init__(f"{key}: {problem}")


def show(value: Any, limit: int = 60) -> str:
    """``repr(value)`` for a one-line message (repr escapes control characters), cut to
    ``limit``."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def check(ok: bool, key: str, problem: str) -> None:
    """:class:`FieldError` ``key: problem`` unless ``ok``."""
    if not ok:
        raise FieldError(key, problem)


def check_positive(obj: Any, *names: str, allow_zero: bool = False) -> None:
    """Each named field of ``obj`` > 0 (>= 0 with ``allow_zero``); None is skipped."""
    for name in names:
        v = getattr(obj, name)
        if v is None:
            continue
        check(v >= 0 if allow_zero else v > 0, name,
              f"must be {'>= 0' if allow_zero else '> 0'}, got {show(v)}")


def check_sizes(obj: Any, *names: str) -> None:
    """Each named field of ``obj`` (a tuple of layer sizes) holds only ints >= 1."""
    for name in names:
        for v in getattr(obj, name):
            check(v >= 1, name, f"layer sizes must be >= 1, got {show(v)}")


class _StrictLoader(yaml.SafeLoader):
    """PyYAML's safe loader refusing duplicate keys and aliases."""

    def compose_node(self, parent, index):  # type: ignore[no-untyped-def]
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.constructor.ConstructorError(
                None, None, f"aliases (*{event.anchor}) are not allowed in a config",
                event.start_mark)
        return super().compose_node(parent, index)

    def construct_mapping(self, node, deep=False):  # type: ignore[no-untyped-def]
        if isinstance(node, yaml.MappingNode):
            seen: set = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=True)
                try:
                    dup = key in seen
                    seen.add(key)
                except TypeError:  # unhashable key: the base class reports it
                    continue
                if dup:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"duplicate key {show(key)}", key_node.start_mark)
        return super().construct_mapping(node, deep)


def _yaml_problem(exc: yaml.YAMLError) -> str:
    if isinstance(exc, yaml.MarkedYAMLError):
        what = " ".join(str(exc.problem or exc.context or "syntax error").split())
        mark = exc.problem_mark or exc.context_mark
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark else ""
        return f"{what}{where}"
    return " ".join(str(exc).split())


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _coerce(value: Any, tp: Any, path: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: expected a mapping, got {type(value).__name__}")
        return from_dict(tp, value, path)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, path)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if len(errors) == 1 else
                          f"{path}: {show(value)} matches none of {_type_name(tp)}")
    if origin is typing.Literal:
        if not isinstance(value, typing.Hashable) or value not in args:
            raise ConfigError(f"{path}: {show(value)} is not one of {list(args)}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path}: expected a list, got {type(value).__name__}")
        item = args[0] if args else Any
        items = [_coerce(v, item, f"{path}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: expected a mapping, got {type(value).__name__}")
        return {k: _coerce(v, args[1], f"{path}.{k if isinstance(k, str) and is_plain_key(k) else show(k)}") for k, v in value.items()} if args else value
    if tp is Any:
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{path}: expected a number, got {show(value)}{_number_hint(value)}")
        try:
            value = float(value)
        except OverflowError:
            value = math.inf
        if not math.isfinite(value):
            raise ConfigError(f"{path}: expected a finite number, got {show(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path}: expected an integer, got {show(value)}")
        if abs(value) >= 1 << 63:
            raise ConfigError(f"{path}: integer out of range, got {show(value)}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: expected true or false, got {show(value)}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path}: expected a string, got {show(value)}")
        return value
    if isinstance(tp, type) and not isinstance(value, tp):
        raise ConfigError(f"{path}: expected {_type_name(tp)}, got {show(value)}")
    return value


def _number_hint(value: Any) -> str:
    """Why a number written in YAML came out as text (YAML 1.1 reads ``3e-4`` as a string)."""
    if isinstance(value, str):
        try:
            number = float(value)
        except ValueError:
            return ""
        if math.isfinite(number):
            return f" (YAML reads it as text: write {number!r})"
    return ""


def from_dict(cls: type[T], data: dict[str, Any], path: str = "") -> T:
    """Build dataclass ``cls`` from a mapping, refusing unknown keys and wrong types (the
    mapping is first passed through ``cls.expand_config`` when the class has one, with paths
    relative to the working directory)."""
    data = _expand_own(cls, data, path, Path("."))
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    kwargs = {}
    for key, value in data.items():
        name = key if isinstance(key, str) and is_plain_key(key) else show(key)
        where = f"{path}.{name}" if path else name
        if not isinstance(key, str) or key not in fields:
            raise ConfigError(f"{where}: unknown key (known: {', '.join(sorted(fields))})")
        kwargs[key] = _coerce(value, hints[key], where)
    try:
        return cls(**kwargs)
    except FieldError as exc:
        raise ConfigError(f"{path + '.' if path else ''}{exc.key}: {exc.problem}") from None
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{path or cls.__name__}: {exc}") from None


def is_plain_key(key: str) -> bool:
    """A key shown as is in messages (short, printable, no spaces)."""
    return 0 < len(key) <= 60 and key.isprintable() and " " not in key


def _cap(message: str, limit: int = MAX_MESSAGE) -> str:
    message = " ".join(message.split())
    limit = max(limit, 40)
    return message if len(message) <= limit else message[:limit - 3] + "..."


def _read_mapping(p: Path, shown: str) -> dict[str, Any]:
    """The top-level mapping of the YAML file ``p`` (shown as ``shown`` in messages), with
    every check of the module doc."""
    try:
        with open(p, "rb") as fh:
            raw = fh.read(MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{shown}: cannot read ({exc.strerror or exc})") from None
    if len(raw) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{shown}: too large for a config (over {MAX_CONFIG_BYTES} bytes)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{shown}: not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset "
                          f"{exc.start}); a config is a YAML text file") from None
    try:
        data = yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as exc:
        raise ConfigError(_cap(f"{shown}: not valid YAML ({_yaml_problem(exc)})")) from None
    except RecursionError:
        raise ConfigError(f"{shown}: not valid YAML (nested too deeply)") from None
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ConfigError(f"{shown}: expected a mapping at the top level")
    return data


def _dataclass_of(tp: Any) -> Any:
    """The config dataclass a field of type ``tp`` holds (``X`` or ``X | None``), else None."""
    if dataclasses.is_dataclass(tp):
        return tp
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        inner = [a for a in typing.get_args(tp) if dataclasses.is_dataclass(a)]
        return inner[0] if len(inner) == 1 else None
    return None


def _expand_own(cls: Any, data: Any, path: str, base: Path) -> Any:
    """``data`` rewritten by the ``expand_config`` classmethod of dataclass ``cls`` (paths
    relative to the folder ``base``), if it has one and ``data`` is a mapping; its
    :class:`FieldError` becomes a :class:`ConfigError` naming the dotted key."""
    hook = getattr(cls, "expand_config", None)
    if hook is None or not isinstance(data, dict):
        return data
    try:
        return hook(data, base)
    except FieldError as exc:
        raise ConfigError(f"{path + '.' if path else ''}{exc.key}: {exc.problem}") from None


def _expand(cls: Any, data: Any, base: Path, path: str = "") -> Any:
    """``data`` (the mapping of dataclass ``cls``, or anything else: returned as is) rewritten
    by the ``expand_config`` classmethods of ``cls`` and of its nested config dataclasses."""
    if not isinstance(data, dict):
        return data
    data = _expand_own(cls, data, path, base)
    hints = typing.get_type_hints(cls)
    out = dict(data)
    for key, value in data.items():
        sub = _dataclass_of(hints.get(key)) if isinstance(key, str) else None
        if sub is not None and isinstance(value, dict):
            out[key] = _expand(sub, value, base, f"{path}.{key}" if path else key)
    return out


def _check_keys(cls: Any, data: dict, path: str = "") -> None:
    """Refuse a key of ``data`` (or of its nested mappings) that names no field of ``cls``
    (nor one of its ``EXPAND_KEYS``). Types and ranges are checked later, on the merged
    config."""
    fields = {f.name for f in dataclasses.fields(cls) if f.init}
    extra = set(getattr(cls, "EXPAND_KEYS", ()))
    hints = typing.get_type_hints(cls)
    for key, value in data.items():
        name = key if isinstance(key, str) and is_plain_key(key) else show(key)
        where = f"{path}.{name}" if path else name
        if not isinstance(key, str) or key not in fields | extra:
            raise ConfigError(f"{where}: unknown key (known: {', '.join(sorted(fields))})")
        if key not in fields:
            continue
        sub = _dataclass_of(hints[key])
        if sub is not None and isinstance(value, dict):
            _check_keys(sub, value, where)


def merge(base: dict, over: dict) -> dict:
    """``over`` merged onto ``base`` (neither is changed): mappings key by key, recursively;
    any other value of ``over`` (a list included) replaces ``base``'s whole."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = value
    return out


def _leaves(data: dict, path: str = "") -> Iterable[str]:
    """Dotted keys of the settings of ``data`` (a mapping's own keys when it is empty)."""
    for key, value in data.items():
        where = f"{path}.{key}" if path else str(key)
        if isinstance(value, dict) and value:
            yield from _leaves(value, where)
        else:
            yield where


def _note(origin: dict[str, str], leaves: Iterable[str], source: str) -> None:
    """Record in ``origin`` (dotted key -> source) that ``source`` set the settings ``leaves``:
    what an earlier layer set at, above or below each of them is replaced."""
    for leaf in leaves:
        for key in [k for k in origin if k.startswith(leaf + ".")]:
            del origin[key]
        parent = leaf.rpartition(".")[0]
        while parent:
            origin.pop(parent, None)
            parent = parent.rpartition(".")[0]
        origin[leaf] = source


def count_settings(data: dict) -> int:
    """Number of settings (leaf values; a list counts as one) of a config mapping, ``extends``
    excluded."""
    return sum(1 for key in _leaves(data) if key != "extends")


class _Composer:
    """Resolves the ``extends`` chains of one config (see the module doc): each file's merged
    mapping (memoised, so a file extended twice is read once) and, for messages, the file or
    override that set each setting last."""

    def __init__(self, cls: Any) -> None:
        self.cls = cls
        self.memo: dict[str, tuple[dict, dict[str, str]]] = {}

    def layer(self, data: dict, where: str, base: Path) -> dict:
        """One layer's mapping (``where`` names it in messages, ``base`` is the folder its
        paths are relative to), expanded and key-checked."""
        try:
            data = _expand(self.cls, data, base)
            _check_keys(self.cls, data)
        except ConfigError as exc:
            raise ConfigError(_cap(f"{where}: {exc}")) from None
        return data

    def resolve(self, p: Path, chain: tuple[str, ...] = ()) -> tuple[dict, dict[str, str]]:
        shown = os.path.normpath(p)
        real = os.path.realpath(p)
        if real in chain:
            names = [os.path.basename(c) for c in chain[chain.index(real):]]
            raise ConfigError(_cap(f"{shown}: extends cycle "
                                   f"({' -> '.join(names + [os.path.basename(real)])})"))
        if len(chain) >= MAX_EXTENDS_DEPTH:
            raise ConfigError(f"{shown}: extends chain deeper than {MAX_EXTENDS_DEPTH} files")
        if real in self.memo:
            return self.memo[real]
        if len(self.memo) >= MAX_EXTENDS_FILES:
            raise ConfigError(f"{shown}: composed of more than {MAX_EXTENDS_FILES} files")
        data = _read_mapping(p, shown)
        bases = data.pop("extends", None)
        if isinstance(bases, str):
            bases = [bases]
        if bases is None:
            bases = []
        if not isinstance(bases, list) or not all(isinstance(b, str) and b.strip()
                                                  for b in bases):
            raise ConfigError(f"{shown}: extends: expected a file or a list of files, got "
                              f"{show(bases)}")
        merged: dict = {}
        origin: dict[str, str] = {}
        for base in bases:
            bp = p.parent / base
            if not bp.is_file():
                raise ConfigError(_cap(f"{shown}: extends: {show(base)}: no such file "
                                       f"({os.path.normpath(bp)})"))
            sub, sub_origin = self.resolve(bp, chain + (real,))
            merged = merge(merged, sub)
            for leaf, source in sub_origin.items():
                _note(origin, [leaf], source)
        own = self.layer(data, shown, p.parent)
        merged = merge(merged, own)
        _note(origin, _leaves(own), shown)
        self.memo[real] = (merged, origin)
        return merged, origin


_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")


def parse_override(token: str) -> tuple[str, Any]:
    """``KEY=VALUE`` (``magail-sumo train --set``) as ``(dotted key, value)``: the value read as
    YAML by the strict loader (``true``, ``5``, ``0.5``, ``null``, ``[a, b]``, ``{k: v}``; text
    otherwise). :class:`ConfigError` naming the token when it is malformed."""
    where = f"--set {show(token)}"
    if len(token) > MAX_OVERRIDE:
        raise ConfigError(f"{where}: longer than {MAX_OVERRIDE} characters")
    key, sep, text = token.partition("=")
    key = key.strip()
    if not sep or not _KEY.fullmatch(key):
        raise ConfigError(f"{where}: expected KEY=VALUE with KEY a dotted setting name "
                          "(e.g. ppo.learning_rate=0.0003)")
    if key == "extends" or key.startswith("extends."):
        raise ConfigError(f"{where}: extends is not a setting (give the file to --config)")
    if not text.strip():
        raise ConfigError(f"{where}: no value (write {key}=null for none)")
    try:
        value = yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as exc:
        raise ConfigError(_cap(f"{where}: value is not valid YAML ({_yaml_problem(exc)})")) \
            from None
    except RecursionError:
        raise ConfigError(f"{where}: value is not valid YAML (nested too deeply)") from None
    return key, value


def _origin_of(key: str, origin: dict[str, str]) -> str | None:
    """The file or override that set the setting ``key`` (or the section holding it)."""
    key = re.sub(r"\[\d+\]", "", key)
    below = next((source for k, source in origin.items() if k.startswith(key + ".")), None)
    if key not in origin and below is not None:  # a mapping given for a setting
        return below
    while key:
        if key in origin:
            return origin[key]
        key = key.rpartition(".")[0]
    return None


def compose_config(path: str | PathLike, cls: type[T], overrides: Iterable[str] = ()
                   ) -> tuple[dict[str, Any], dict[str, str]]:
    """The merged mapping of the config file ``path`` (its ``extends`` resolved, then the
    ``KEY=VALUE`` ``overrides``, merged in order into one layer) before it is typed, and the
    file or override that set each setting (dotted key -> name). Unknown keys are refused
    naming their file or override; types and ranges are checked by :func:`load_config`."""
    merged, origin = _Composer(cls).resolve(Path(path))
    origin = dict(origin)
    layer: dict = {}
    set_by: dict[str, str] = {}
    for token in overrides:
        key, value = parse_override(token)
        one: Any = value
        for part in reversed(key.split(".")):
            one = {part: one}
        try:
            _check_keys(cls, one)
        except ConfigError as exc:
            raise ConfigError(_cap(f"--set {show(token)}: {exc}")) from None
        layer = merge(layer, one)
        _note(set_by, _leaves(one), f"--set {show(token)}")
    if layer:
        try:
            layer = _expand(cls, layer, Path("."))
        except ConfigError as exc:
            source = _origin_of(str(exc).split(": ", 1)[0], set_by) or "--set"
            raise ConfigError(_cap(f"{source}: {exc}")) from None
        merged = merge(merged, layer)
        for leaf in _leaves(layer):
            _note(origin, [leaf], set_by.get(leaf) or _origin_of(leaf, set_by) or "--set")
    return merged, origin


def load_config(path: str | PathLike, cls: type[T], overrides: Iterable[str] = ()) -> T:
    """Load a YAML file into dataclass ``cls``, its ``extends`` resolved and the ``KEY=VALUE``
    ``overrides`` applied (module doc); errors name the file and key (and the file or
    override that set a refused value, when it is not the file itself)."""
    p = Path(path)
    merged, origin = compose_config(p, cls, overrides)
    try:
        return from_dict(cls, merged)
    except ConfigError as exc:
        message = f"{p}: {exc}"
        source = _origin_of(str(exc).split(": ", 1)[0], origin)
        if source is None or source == os.path.normpath(p):
            raise ConfigError(_cap(message)) from None
        note = _cap(f"(from {source})" if source.startswith("--set") else f"(set in {source})",
                    MAX_MESSAGE // 2)
        raise ConfigError(f"{_cap(message, MAX_MESSAGE - len(note) - 1)} {note}") from None


def to_dict(config: Any) -> dict[str, Any]:
    """Plain-data (YAML-safe) form of a config dataclass."""
    def plain(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        return v
    return plain(config)


def environment_versions() -> dict[str, str]:
    """Versions of Python and of the packages a run depends on."""
    from importlib import metadata

    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for pkg in ("magail-sumo", "numpy", "torch", "stable-baselines3", "pettingzoo", "gymnasium",
                "eclipse-sumo", "libsumo", "numba", "protobuf"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def git_commit(repo: str | PathLike | None = None) -> str | None:
    """The current git commit of the source tree (with '-dirty' when modified), if any."""
    cwd = Path(repo) if repo else Path(__file__).resolve().parent
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True,
                             text=True, timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=cwd,
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return sha + ("-dirty" if dirty else "")


def record_run(run_dir: str | PathLike, config: Any) -> Path:
    """Write ``config.yaml`` and ``environment.json`` (versions, git commit) into ``run_dir``."""
    d = Path(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    write_text(d / "config.yaml", yaml.safe_dump(to_dict(config), sort_keys=False))
    env = {"versions": environment_versions(), "git_commit": git_commit(),
           "command": sys.argv}
    write_text(d / "environment.json", json.dumps(env, indent=2))
    return d
