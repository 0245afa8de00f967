"""Locating the SUMO binaries: the eclipse-sumo wheel's (the SUMO this package installed),
else ``$SUMO_HOME/bin``, else ``PATH``.

The wheel comes first so that a ``magail-sumo`` run from a virtual environment that is not
activated (cron, an IDE, an absolute path) starts the same SUMO as libsumo, not another one
found on ``PATH``.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from magail_sumo.errors import MagailSumoError


class SumoBinaryMissing(MagailSumoError):
    """A SUMO binary is not installed; the message is one line."""


def binary(name: str) -> str:
    """Path of SUMO binary ``name`` (``netconvert``, ``sumo``)."""
    try:
        import sumo  # eclipse-sumo wheel
        path = Path(sumo.SUMO_HOME) / "bin" / name
        if path.exists():
            return str(path)
    except ImportError:
        pass
    home = os.environ.get("SUMO_HOME")
    if home and (Path(home) / "bin" / name).exists():
        return str(Path(home) / "bin" / name)
    found = shutil.which(name)
    if not found:
        raise SumoBinaryMissing(f"{name} not found (install eclipse-sumo or set SUMO_HOME)")
    return found
