"""OpenDRIVE export of a converted network (``magail-sumo convert --opendrive``).

netconvert writes the SUMO network as OpenDRIVE 1.4 (``--sumo-net-file NET
--opendrive-output XODR``): roads with their lanes, widths, speeds and junction connections, in
the network's (= the recording's) coordinates. Tools such as CARLA, esmini or SMARTS read it.
:func:`read_back` imports an ``.xodr`` with netconvert again (``--opendrive-files``), as the
tests do to check the export.
"""

from __future__ import annotations

from pathlib import Path

from .tools import run_tool


def write_opendrive(net_file: str | Path, xodr_file: str | Path,
                    timeout_s: float | None = None) -> list[str]:
    """Write ``xodr_file`` from SUMO network ``net_file``; returns netconvert's warning lines.

    netconvert runs in the output folder with bare file names when both files are there (so
    nothing in the output names a temporary folder).

    :raises converters.sumo.tools.SumoToolError: netconvert failed or ran past ``timeout_s``.
    """
    net, xodr = Path(net_file), Path(xodr_file)
    same = net.parent.resolve() == xodr.parent.resolve()
    cwd = xodr.parent if same else None
    args = ["--sumo-net-file", net.name if same else str(net),
            "--opendrive-output", xodr.name if same else str(xodr)]
    return run_tool("netconvert", args, cwd=cwd, timeout_s=timeout_s)


def read_back(xodr_file: str | Path, net_file: str | Path,
              timeout_s: float | None = None) -> list[str]:
    """Import ``xodr_file`` with netconvert into SUMO network ``net_file``; its warnings."""
    return run_tool("netconvert", ["--opendrive-files", str(xodr_file), "-o", str(net_file)],
                    timeout_s=timeout_s)
