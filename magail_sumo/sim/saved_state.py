"""Saved SUMO states that load again: the routes a scaled demand's copies lose.

With ``--scale`` above 1 SUMO adds copies of a scenario's vehicles (``<id>.1``, ...) that
share their original's route (``!<id>``, the route a vehicle defines inside itself). SUMO 1.28
writes that route into a saved state only while the original is in the network, so a state
saved after the original has arrived holds a copy whose route is named nowhere, and loading it
fails (``Error: The route '!150535_418_0' for vehicle '150535_418_0.1' is not known.``; seen on
cologne8 at ``--scale 2``). :func:`mend_routes` writes each such route into the state from the
running simulation that saved it (the copy's own route now, which is that route: a vehicle that
is rerouted gets a route of its own, and the state names it).

Pure text work on the state file (plain or gzipped XML, as SUMO wrote it), plus one
``vehicle.getRoute`` per copy that lost its route.
"""

from __future__ import annotations

import gzip
import re
from collections.abc import Callable
from pathlib import Path
from xml.sax.saxutils import quoteattr, unescape

_ROUTE = re.compile(r'<route id="([^"]*)"')
_VEHICLE = re.compile(r'<vehicle id="([^"]*)"[^>]*?\sroute="([^"]*)"')


#: the attribute-value entities XML writes beyond ``unescape``'s own (&amp; &lt; &gt;)
_QUOTES = {"&quot;": '"', "&apos;": "'"}


def _unescape(s: str) -> str:
    return unescape(s, _QUOTES)


def lost_routes(text: str) -> dict[str, str]:
    """Route id -> the first vehicle of state ``text`` that names it, for the routes a
    vehicle defined inside itself (``!`` ids: the scenario's named routes load from its own
    files) that no ``<route>`` of the state defines (ids unescaped)."""
    defined = {_unescape(m.group(1)) for m in _ROUTE.finditer(text)}
    lost: dict[str, str] = {}
    for m in _VEHICLE.finditer(text):
        vid, route = _unescape(m.group(1)), _unescape(m.group(2))
        if route.startswith("!") and route not in defined:
            lost.setdefault(route, vid)
    return lost


def mend_routes(path: str | Path, route_of: Callable[[str], list[str] | tuple[str, ...]]
                ) -> int:
    """Write into the saved state ``path`` each route its vehicles name that it does not
    define (module doc), with the edges ``route_of(vehicle)`` gives (``vehicle.getRoute`` of
    the simulation that saved it). Returns how many routes were written."""
    path = Path(path)
    gz = path.suffix == ".gz"
    raw = path.read_bytes()
    text = (gzip.decompress(raw) if gz else raw).decode("utf-8")
    lost = lost_routes(text)
    if not lost:
        return 0
    lines = "".join(f'    <route id={quoteattr(r)} state="0" '
                    f'edges={quoteattr(" ".join(route_of(v)))}/>\n' for r, v in lost.items())
    at = text.find("<vehicle ")
    at = text.rfind("\n", 0, at) + 1  # the start of the first vehicle's line
    text = text[:at] + lines + text[at:]
    data = text.encode("utf-8")
    path.write_bytes(gzip.compress(data) if gz else data)
    return len(lost)
