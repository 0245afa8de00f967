"""Locating and running the SUMO binaries (from the eclipse-sumo wheel, else PATH)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path


class SumoToolError(RuntimeError):
    """A SUMO binary is missing or failed; the message is one line."""


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
        raise SumoToolError(f"{name} not found (install eclipse-sumo or set SUMO_HOME)")
    return found


def run_tool(name: str, args: list[str], cwd: Path | None = None,
             timeout_s: float | None = None) -> list[str]:
    """Run a SUMO binary; returns its warning lines; raises :class:`SumoToolError` on failure
    (or when it runs longer than ``timeout_s`` seconds: it is killed then)."""
    try:
        proc = subprocess.run([binary(name), *args], cwd=cwd, capture_output=True, text=True,
                              timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise SumoToolError(f"{name} timed out after {timeout_s:.0f} s (killed)") from None
    lines = (proc.stdout + proc.stderr).splitlines()
    if proc.returncode != 0:
        errors = [ln for ln in lines if ln.startswith("Error")] or lines[-1:] or ["no output"]
        raise SumoToolError(f"{name} failed (exit {proc.returncode}): {errors[0]}")
    return [ln for ln in lines if ln.startswith("Warning")]
