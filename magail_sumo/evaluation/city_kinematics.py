"""Speed and acceleration distributions of a city run's drivers, against recorded humans.

Two groups of drivers are sampled: the **agents** of a policy's city run
(:func:`~magail_sumo.evaluation.city.run_policy`; their bicycle speed every 0.1-s step) and
**SUMO's drivers** in SUMO's own run of the same window (``sumo``, every vehicle SUMO-driven;
their speed every second from an FCD output, :func:`fcd_group`), both restricted to the vehicle
classes that may be agents. A vehicle's acceleration is its speed change over
:data:`ACCEL_WINDOW_S` (1 s), for vehicles seen at both ends: over a second, the detection noise
of recorded positions and a policy's sampling noise average out alike. The counts fall on the bins of :data:`~magail_sumo.evaluation.traffic.distributions.BINS`
(speed 0..30 m/s, acceleration ±10 m/s², outliers in the end bins), and each group's
Jensen–Shannon divergence (bits, in [0, 1]) from the **recorded humans**' distribution is the
figure: the expert data of recorded scenes (``magail-sumo expert``), whose speeds are the
replayed vehicles' (recorded displacement per 0.1 s) and whose accelerations are their speed
changes over the same 1 s.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections import deque
from pathlib import Path

import numpy as np

from magail_sumo.evaluation.traffic.distributions import BINS, counts, js_divergence
from magail_sumo.expert.dataset import ExpertDataset

#: (feature of ``BINS``, the name in ``city.json`` / ``kinematics.json``)
FEATURES = (("linear_speed", "speed"), ("linear_acceleration", "accel"))
#: seconds over which an acceleration is a speed change
ACCEL_WINDOW_S = 1.0


class Group:
    """Counts of one group of drivers (module doc); ``add`` once per step."""

    def __init__(self, dt: float) -> None:
        self.dt = dt
        self.lag = max(1, round(ACCEL_WINDOW_S / dt))
        #: speeds by id of the last ``lag`` steps, oldest first
        self.history: deque[dict[str, float]] = deque(maxlen=self.lag)
        self.counts = {name: np.zeros(BINS[f][2], np.int64) for f, name in FEATURES}

    def add(self, ids: list[str], speed: np.ndarray) -> None:
        """The step's vehicles ``ids`` with their (V,) speeds (m/s)."""
        speed = np.asarray(speed, np.float64)
        self.counts["speed"] += counts(speed, "linear_speed")
        if len(self.history) == self.lag:  # per id: matched to ``lag`` steps ago by string id
            old = self.history[0]
            then = np.array([old.get(v, np.nan) for v in ids], np.float64)
            accel = (speed - then) / (self.lag * self.dt)
            self.counts["accel"] += counts(accel[np.isfinite(accel)], "linear_acceleration")
        self.history.append(dict(zip(ids, speed.tolist())))

    def as_json(self) -> dict:
        return {name: c.tolist() for name, c in self.counts.items()}


def fcd_group(fcd: str | Path, classes: tuple[str, ...], vtypes: dict[str, str]) -> Group:
    """The :class:`Group` of the vehicles of an FCD file sampled every :data:`ACCEL_WINDOW_S`
    (``--device.fcd.period``) whose type's class (``vtypes``: type id -> class) is one of
    ``classes``; streamed (one time step in memory)."""
    group = Group(ACCEL_WINDOW_S)
    ids: list[str] = []
    speed: list[float] = []
    for _, el in ET.iterparse(str(fcd), events=("end",)):
        if el.tag == "vehicle":
            if vtypes.get(el.get("type", ""), "passenger") in classes:
                ids.append(el.get("id", ""))
                speed.append(float(el.get("speed", "nan")))
        elif el.tag == "timestep":
            group.add(ids, np.array(speed))
            ids, speed = [], []
            el.clear()
    return group


def js(group: dict, humans: dict | None) -> dict[str, float]:
    """Per feature name, the JS divergence (bits) of counts ``group`` from counts ``humans``
    (NaN without humans or samples)."""
    out = {}
    for _, name in FEATURES:
        g = np.asarray(group.get(name, ()), np.float64)
        h = None if humans is None else np.asarray(humans[name], np.float64)
        if h is None or not g.sum() or not h.sum():
            out[name] = float("nan")
        else:
            out[name] = js_divergence(g / g.sum(), h / h.sum())
    return out


def human_counts(expert_dir: str | Path) -> dict:
    """Counts of the recorded humans of ``expert_dir`` (what ``magail-sumo expert`` wrote):
    the speed of every transition, and the speed change over :data:`ACCEL_WINDOW_S` of each
    vehicle recorded at both ends (0.1-s log steps)."""
    data = ExpertDataset(expert_dir)
    speed = data.s[:, data.observation_names.index("speed")].astype(np.float64)
    lag = round(ACCEL_WINDOW_S / 0.1)
    # the same vehicle (scene, track) lag steps later: a sorted lookup over all transitions
    key = (data.scene.astype(np.int64) * (1 << 40) + data.track.astype(np.int64) * (1 << 16)
           + data.step.astype(np.int64))
    order = np.argsort(key)
    later = key + lag
    pos = np.clip(np.searchsorted(key[order], later), 0, len(key) - 1)
    found = key[order][pos] == later
    accel = (speed[order][pos] - speed) / ACCEL_WINDOW_S
    return {"speed": counts(speed, "linear_speed").tolist(),
            "accel": counts(accel[found], "linear_acceleration").tolist(),
            "source": str(expert_dir), "transitions": len(data)}
