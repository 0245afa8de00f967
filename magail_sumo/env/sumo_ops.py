"""libsumo vehicle operations the env needs beyond :class:`~magail_sumo.sim.session.SumoSession`.

(Candidates for ``SumoSession`` methods; kept here so the session module stays untouched.)
"""

from __future__ import annotations


def remove_vehicle(vid: str) -> None:
    """Take a vehicle out of the simulation (no-op when it already left or never entered).

    Its subscription goes first: libsumo fails the next step ("Vehicle ... is not known") when
    a subscribed vehicle is removed.
    """
    import libsumo

    try:
        libsumo.vehicle.unsubscribe(vid)
        libsumo.vehicle.remove(vid)
    except Exception:  # libsumo raises its own types; gone already is fine
        pass

