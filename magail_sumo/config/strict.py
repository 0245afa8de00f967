"""Run configuration as data: typed dataclasses loaded from YAML with strict checking.

Every key of a YAML file must name a field of the target dataclass (nested dataclasses for
nested mappings) and every value must have the field's type; anything else is refused with a
:class:`ConfigError` naming the file, the key path and the problem. Nothing is guessed or
silently ignored. Numbers must be finite (no ``.nan`` / ``.inf``); value ranges are checked by
the dataclasses' ``__post_init__`` (raising :class:`FieldError`, reported with the dotted key).
The YAML must be UTF-8 text of at most :data:`MAX_CONFIG_BYTES`, with no duplicate keys and no
aliases (``*name``: a few hundred bytes of nested aliases expand to gigabytes). Error messages
are one line of bounded length.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from magail_sumo.errors import MagailSumoError
from magail_sumo.inputs import InputFileError, open_regular

T = TypeVar("T")


#: largest config file read (bytes)
MAX_CONFIG_BYTES = 1 << 20
#: longest :class:`ConfigError` message :func:`~magail_sumo.config.load_config` gives (characters)
MAX_MESSAGE = 400


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
            return f" (YAML reads it as text: write {yaml_float(number)})"
    return ""


def yaml_float(number: float) -> str:
    """``number`` as YAML 1.1 reads a float: Python's shortest form, with a dot in the mantissa
    of an exponent form (``1e-12`` is text to YAML 1.1, ``1.0e-12`` a float)."""
    text = repr(float(number))
    mantissa, e, exponent = text.partition("e")
    if e and "." not in mantissa:
        text = f"{mantissa}.0e{exponent}"
    return text


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
    try:  # a regular file only: a FIFO would block, a device stream
        with open_regular(p, expected="a config file") as fh:
            raw = fh.read(MAX_CONFIG_BYTES + 1)
    except InputFileError as exc:
        raise ConfigError(f"{shown}: {exc.problem}") from None
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
