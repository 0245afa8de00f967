"""Configs that compose. A file may start from others: ``extends: FILE`` or ``extends: [FILE, ...]``
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

import os
import re
import stat
import typing
from os import PathLike
from pathlib import Path
from typing import Any, Iterable

import yaml

from magail_sumo.inputs import path_problem

from .strict import (MAX_MESSAGE, ConfigError, T, _cap, _check_keys, _dataclass_of,
                     _expand_own, _read_mapping, _StrictLoader, _yaml_problem, from_dict, show)

#: longest chain of ``extends`` (a file extending a file extending ...), the first file included
MAX_EXTENDS_DEPTH = 32
#: most distinct files one config may be composed of
MAX_EXTENDS_FILES = 64
#: longest ``--set KEY=VALUE`` token (characters)
MAX_OVERRIDE = 10_000



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
            problem, st = path_problem(bp)
            if problem or stat.S_ISDIR(st.st_mode):  # a FIFO is named as one, not "missing"
                raise ConfigError(_cap(f"{shown}: extends: {show(base)}: "
                                       f"{problem or 'is a directory'} "
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
