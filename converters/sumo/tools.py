"""Running the SUMO binaries (located by :func:`magail_sumo.sim.binaries.binary`)."""

from __future__ import annotations

import subprocess
from pathlib import Path

from magail_sumo.sim.binaries import SumoBinaryMissing, binary


class SumoToolError(RuntimeError):
    """A SUMO binary is missing or failed; the message is one line."""


def run_tool(name: str, args: list[str], cwd: Path | None = None,
             timeout_s: float | None = None) -> list[str]:
    """Run a SUMO binary; returns its warning lines; raises :class:`SumoToolError` on failure
    (or when it runs longer than ``timeout_s`` seconds: it is killed then)."""
    try:
        exe = binary(name)
    except SumoBinaryMissing as exc:
        raise SumoToolError(str(exc)) from None
    try:
        proc = subprocess.run([exe, *args], cwd=cwd, capture_output=True, text=True,
                              timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise SumoToolError(f"{name} timed out after {timeout_s:.0f} s (killed)") from None
    lines = (proc.stdout + proc.stderr).splitlines()
    if proc.returncode != 0:
        errors = [ln for ln in lines if ln.startswith("Error")] or lines[-1:] or ["no output"]
        raise SumoToolError(f"{name} failed (exit {proc.returncode}): {errors[0]}")
    return [ln for ln in lines if ln.startswith("Warning")]
