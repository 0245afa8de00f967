"""Quality figures of a converted scene (definitions in conversion.json / issue 3).

* on_network_rate (:func:`on_network`): share of valid states of moving vehicles lying within half the lane width
  + 0.5 m of a lane (junction-internal lanes included) whose direction is within 45° of the
  vehicle heading.
* route_rate: share of moving vehicles whose route is connected and covers >= 90 % of their
  valid states (same test, restricted to the route's lanes and the internal lanes between).
* signal_fidelity / sumo_baseline: from one SUMO run of the scenario
  (:func:`converters.sumo.baseline.run_baseline`).
"""

from __future__ import annotations

import numpy as np

from magail_sumo.scene import ObjectType, Scene

from .lanes import LaneSegments, on_lanes
from .routes import PARKED_MOVE, VehicleRoute, moved_distance, route_covers

COVERAGE = 0.9  #: share of its states a route must cover (route_rate)
#: the bar each figure of a usable conversion meets (a figure that is None, e.g. signal
#: fidelity of a scene without signals, is not judged)
BARS: dict[str, float] = {"on_network_rate": 0.98, "route_rate": 0.95, "signal_fidelity": 0.99}


def failed_bars(quality: dict) -> list[str]:
    """Names of the :data:`BARS` a conversion's ``quality`` figures fall below (in the
    order of ``BARS``); figures that are absent or None are not judged."""
    out = []
    for name, bar in BARS.items():
        value = quality.get(name)
        if isinstance(value, (int, float)) and value < bar:
            out.append(name)
    return out


def moving_vehicles(scene: Scene) -> np.ndarray:
    """Indices of vehicle tracks that move more than :data:`PARKED_MOVE` m."""
    return np.flatnonzero((scene.tracks.type == ObjectType.VEHICLE)
                          & (moved_distance(scene) > PARKED_MOVE))


def on_network(scene: Scene, seg: LaneSegments, carried: np.ndarray | None = None
               ) -> tuple[float | None, float | None, list[dict]]:
    """``(on_network_rate, the same with the states in carried counted as off, the vehicles
    behind a rate below 1)`` from one pass over the valid states of the moving vehicles.

    ``on_network_rate``: see the module doc; None when there are no moving vehicles.
    ``carried`` (N, T) bool: states counted as off the network whatever ``seg`` says (those
    carried by synthesised lanes: the map-only figure). The vehicles, most states off first:
    ``{"track": id, "off": states off every lane, "of": its valid states}``."""
    tr = scene.tracks
    idx = moving_vehicles(scene)
    v = tr.valid[idx]
    if not v.any():
        return None, None, []
    xy = np.stack([tr.x[idx][v], tr.y[idx][v]], axis=1)
    on = on_lanes(seg, xy, tr.heading[idx][v].astype(np.float64))
    map_only = on & ~carried[idx][v] if carried is not None else on
    rows = np.nonzero(v)[0]  # the moving vehicle of each valid state (row-major order)
    off = np.bincount(rows, ~on, minlength=len(idx)).astype(int)
    out = [{"track": int(tr.id[n]), "off": int(o), "of": int(c)}
           for n, o, c in zip(idx.tolist(), off.tolist(), v.sum(axis=1).tolist()) if o]
    out.sort(key=lambda m: (-m["off"], m["track"]))
    return float(on.mean()), float(map_only.mean()), out


#: m/s, a state moving at least this fast against its heading is reversing
REVERSING_SPEED = 0.5


def route_quality(scene: Scene, seg: LaneSegments, routes: list[VehicleRoute], net,
                  off_network: list[dict], unconverted: list[dict] = ()
                  ) -> tuple[float | None, list[dict]]:
    """``route_rate`` (module doc; None when there are no moving vehicles) and
    :func:`route_misses`, from one pass over the moving vehicles."""
    moving = moving_vehicles(scene)
    misses = route_misses(scene, seg, routes, net, off_network, moving, unconverted)
    return (1.0 - len(misses) / len(moving) if len(moving) else None), misses


def route_misses(scene: Scene, seg: LaneSegments, routes: list[VehicleRoute], net,
                 off_network: list[dict], moving: np.ndarray | None = None,
                 unconverted: list[dict] = ()) -> list[dict]:
    """The moving vehicles (``moving``: their rows, default :func:`moving_vehicles`) behind a
    route rate below 1, each ``{"track": its id, "reason": ...}`` (track order). Reasons:

    * ``no route: <why>`` -- the conversion made none (why as in ``unconverted``);
    * ``no connected lane sequence`` -- its matched lanes are not joined in the network;
    * ``covers X of its states (off the network at A, reversing at B, on other lanes at C)``
      -- the shares of its valid states lying on no lane of the network (``off_network``, the
      vehicles :func:`on_network` found off it: off-map driving), moving backwards (velocity
      against the heading faster than :data:`REVERSING_SPEED`), and on lanes that are not its
      route's."""
    off_share = {m["track"]: m["off"] / m["of"] for m in off_network}
    by_track = {r.track: r for r in routes}
    why = {u.get("id"): u.get("reason", "") for u in unconverted
           if u.get("kind") in ("vehicle", "cyclist")}
    tr = scene.tracks
    out = []
    if moving is None:
        moving = moving_vehicles(scene)
    for n in moving.tolist():  # once per conversion, per moving vehicle
        r = by_track.get(n)
        tid = int(tr.id[n])
        if r is None:
            reason = f"no route: {why.get(tid, 'not converted')}"
        elif not r.connected:
            reason = "no connected lane sequence"
        else:
            cover = route_covers(scene, seg, r, net)
            if cover >= COVERAGE:
                continue
            steps = np.flatnonzero(tr.valid[n])
            heading = tr.heading[n, steps].astype(np.float64)
            off = off_share.get(tid, 0.0)
            along = tr.vx[n, steps] * np.cos(heading) + tr.vy[n, steps] * np.sin(heading)
            back = float((along < -REVERSING_SPEED).mean())
            other = max(0.0, 1.0 - cover - off)
            reason = (f"covers {cover:.2f} of its states (off the network at {off:.2f}, "
                      f"reversing at {back:.2f}, on other lanes at {other:.2f})")
        out.append({"track": tid, "reason": reason})
    return out
