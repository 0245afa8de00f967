"""Train / test splits of scene files (``configs/splits/*.yaml``): the generalisation protocol.

A split names the scene files a policy may be trained on and the held-out files every quality
figure is measured on (docs/evaluation-and-realism.md, "Generalisation protocol"). It is a strict config
(:func:`magail_sumo.config.load_config`: unknown or duplicate keys, aliases and wrong types are
refused) and checked when loaded: both lists non-empty, no file twice, and no test scene that is
also a training scene — the same path, or a file of the same scene in another format (the same
file name stem, e.g. ``data/womd/X.tfrecord`` and ``data/scenarionet/X.pkl``).

A split of scenes that are not bundled in ``data/`` names where they are with ``data_root``: a
folder (relative to the repository root, or absolute) the relative scene paths are under. It may
read an environment variable the shell way, ``${NAME}`` or ``${NAME:-default}``, so that one split
file serves every machine (``configs/splits/wild.yaml``: ``${MAGAIL_SUMO_SHARED_DATA:-../shared/
data}``).

This module sits low (it imports only :mod:`magail_sumo.config`) so that a training config can
take its scenes from a split (``scenes: {split: FILE, part: train}``, :class:`~magail_sumo.
training.config.ScenesConfig`) and evaluation reads the same file.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from os import PathLike
from pathlib import Path

from magail_sumo.config import ConfigError, check, load_config

#: the parts of a split
PARTS: tuple[str, ...] = ("train", "test")

_VAR = re.compile(r"\$\{([A-Za-z_][A-Za-z0-9_]*)(?::-([^}]*))?\}")


def expand_root(text: str) -> str:
    """``text`` with each ``${NAME}`` / ``${NAME:-default}`` replaced by the environment
    variable ``NAME`` (the default where it is unset or empty).

    :raises ConfigError: ``NAME`` is unset and has no default, or a ``$`` is not of that form.
    """
    def one(m: re.Match) -> str:
        value = os.environ.get(m.group(1), "")
        if value:
            return value
        if m.group(2) is None:
            raise ConfigError(f"data_root: environment variable {m.group(1)} is not set "
                              "(and the split gives no default: ${NAME:-default})")
        return m.group(2)
    out = _VAR.sub(one, text)
    check("$" not in _VAR.sub("", text), "data_root",
          f"{text!r}: only ${{NAME}} and ${{NAME:-default}} are expanded")
    return out


def scene_stem(path: str) -> str:
    """A scene file's name without folder and scene-file extensions (``.tfrecord[.gz]``,
    ``.pkl``): files of one scene in two formats share it."""
    name = os.path.basename(os.path.normpath(path))
    for ext in (".gz", ".tfrecord", ".pkl"):
        name = name[:-len(ext)] if name.endswith(ext) else name
    return name


@dataclass(frozen=True)
class SceneSplit:
    """Scene files for training and for the held-out evaluation.

    :param train: scene files a policy may be trained on (WOMD TFRecords, ScenarioNet pickles;
        paths relative to the repository root, or absolute).
    :param test: held-out scene files, never trained on; quality figures are measured here.
    :param description: free text.
    :param data_root: the folder relative scene paths are under (module doc; empty: the
        repository root, i.e. the ``root`` given to :meth:`files`).
    """

    train: tuple[str, ...]
    test: tuple[str, ...]
    description: str = ""
    data_root: str = ""

    def __post_init__(self) -> None:
        for key in PARTS:
            files = getattr(self, key)
            check(len(files) > 0, key, "needs at least one scene file")
            norm = [os.path.normpath(f) for f in files]
            dup = next((f for k, f in enumerate(norm) if f in norm[:k]), None)
            check(dup is None, key, f"{dup} is listed twice")
        train = {os.path.normpath(f): f for f in self.train}
        train_stems = {scene_stem(f): f for f in self.train}
        for f in self.test:
            check(os.path.normpath(f) not in train, "test", f"{f} is also a training scene")
            check(scene_stem(f) not in train_stems, "test",
                  f"{f} is the same scene as training file {train_stems.get(scene_stem(f))}")

        if self.data_root:
            expand_root(self.data_root)  # an unusable root is refused when loaded

    def base(self, root: str | PathLike = ".") -> Path:
        """The folder relative scene paths are under: ``data_root`` resolved against ``root``
        (the repository root) where relative, or ``root`` itself without one."""
        return Path(root) / expand_root(self.data_root) if self.data_root else Path(root)

    def paths(self, which: str, root: str | PathLike = ".") -> list[Path]:
        """The ``train`` or ``test`` paths, relative ones under :meth:`base`. Not checked to
        exist."""
        if which not in PARTS:
            raise ConfigError(f"split part {which!r}: must be 'train' or 'test'")
        base = self.base(root)
        return [Path(f) if os.path.isabs(f) else base / f for f in getattr(self, which)]

    def files(self, which: str, root: str | PathLike = ".") -> list[Path]:
        """:meth:`paths`, each checked to be a file.

        :raises ConfigError: ``which`` is neither, or a file does not exist (naming it).
        """
        out = self.paths(which, root)
        for k, (f, p) in enumerate(zip(getattr(self, which), out)):
            if not p.is_file():
                raise ConfigError(f"split {which}[{k}]: {f}: no such file (under "
                                  f"{self.base(root)})")
        return out


def load_split(path: str | PathLike) -> SceneSplit:
    """Read a split file (strict YAML, see the module doc); :class:`ConfigError` naming the
    file and key otherwise."""
    return load_config(path, SceneSplit)
