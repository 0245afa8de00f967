"""The run record: the fully resolved config (``config.yaml``) and the versions and git commit it
ran with (``environment.json``), written into a run's folder."""

from __future__ import annotations

import json
import platform
import subprocess
import sys
from os import PathLike
from pathlib import Path
from typing import Any

import yaml

from magail_sumo.outputs import inside, write_text

from .strict import to_dict


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
    """Write ``config.yaml`` and ``environment.json`` (versions, git commit) into ``run_dir``
    (made when missing); :class:`~magail_sumo.outputs.OutputError` when either is a symbolic
    link out of it (:func:`~magail_sumo.outputs.inside`)."""
    d = Path(run_dir)
    d.mkdir(parents=True, exist_ok=True)
    write_text(inside(d, "config.yaml"), yaml.safe_dump(to_dict(config), sort_keys=False))
    env = {"versions": environment_versions(), "git_commit": git_commit(),
           "command": sys.argv}
    write_text(inside(d, "environment.json"), json.dumps(env, indent=2))
    return d
