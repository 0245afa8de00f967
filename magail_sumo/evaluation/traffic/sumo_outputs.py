"""City-scale traffic figures of a plain SUMO scenario, from SUMO's own outputs.

:func:`run_sumo_outputs` runs a ``.sumocfg`` (the ``sumo`` binary for the SUMO-default run, or
a :class:`~magail_sumo.sim.session.SumoSession` in a fresh process with a controller callback
for a controlled run) writing
``tripinfo.xml``, ``edgedata.xml`` and ``statistics.xml``, and :func:`summarise` reads them
(sumolib) into a :class:`SumoRunSummary`. :func:`compare_runs` puts runs side by side (pandas).
:func:`output_args` gives the three output options alone, for a run started elsewhere (the
city env's ``sumo_args``).

A vehicle taken out of SUMO before its trip's end (``vaporized`` in its tripinfo: removed
through TraCI / libsumo, or by a collision action) has not arrived and is left out of the trip
figures, unless the caller names it as completed (a controller that removes vehicles at their
destination).
"""

from __future__ import annotations

import importlib
import subprocess
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Collection, Sequence

import numpy as np

from magail_sumo.errors import MagailSumoError
from magail_sumo.inputs import InputFileError, regular_file
from magail_sumo.sim.binaries import SumoBinaryMissing, binary
from magail_sumo.sim.session import SessionConfig, SumoSession
from magail_sumo.sim.sumo_config import SumoConfigError, read_config
from magail_sumo.workers import run_one


class SumoRunError(MagailSumoError):
    """A SUMO run of a scenario failed (one line naming the config)."""


@dataclass(frozen=True)
class SumoRunSummary:
    """Aggregates of one SUMO run.

    :param arrived: vehicles that finished their trip.
    :param travel_time_s: mean trip duration of the arrived vehicles (s).
    :param waiting_time_s: mean time spent at speed < 0.1 m/s per arrived vehicle (s).
    :param time_loss_s: mean time lost against driving at the allowed speed (s).
    :param throughput_veh_h: arrived vehicles per simulated hour.
    :param mean_edge_speed_mps: mean speed over edges, weighted by sampled seconds (m/s).
    :param teleports: vehicles teleported (jams, collisions, wrong lanes).
    :param duration_s: simulated time (s).
    :param collisions: collisions SUMO detected (``statistics.xml`` ``<safety collisions>``;
        0 where the statistics do not say).
    """

    arrived: int
    travel_time_s: float
    waiting_time_s: float
    time_loss_s: float
    throughput_veh_h: float
    mean_edge_speed_mps: float
    teleports: int
    duration_s: float
    collisions: int = 0


def _outputs(out: Path) -> dict[str, Path]:
    return {"tripinfo": out / "tripinfo.xml", "edgedata": out / "edgedata.xml",
            "statistics": out / "statistics.xml"}


#: SUMO's per-step summary (vehicles running, waiting, ...): the report's vehicles-over-time
#: figure; optional (runs before it was written have none)
SUMMARY_FILE = "summary.xml"


def output_args(out: str | Path) -> list[str]:
    """SUMO options writing the three outputs (and the per-step summary) into ``out``."""
    o = _outputs(Path(out))
    return ["--tripinfo-output", str(o["tripinfo"]), "--edgedata-output", str(o["edgedata"]),
            "--statistic-output", str(o["statistics"]),
            "--summary-output", str(Path(out) / SUMMARY_FILE)]


def sumo_options(out: Path, begin: float | None, end: float | None, seed: int,
                 extra_args: Sequence[str] = ()) -> list[str]:
    """The options of a run writing the three outputs into ``out``, beyond those every
    :class:`~magail_sumo.sim.session.SumoSession` passes (``--no-step-log``, ``--no-warnings``)."""
    opts = [*output_args(out), "--seed", str(seed), "--duration-log.disable", "true"]
    if begin is not None:
        opts += ["--begin", str(begin)]
    if end is not None:
        opts += ["--end", str(end)]
    return opts + list(extra_args)


def sumo_command(sumocfg: Path, out: Path, begin: float | None, end: float | None, seed: int,
                 extra_args: Sequence[str] = (), private: Path | None = None) -> list[str]:
    """The installed ``sumo`` binary's command line running ``sumocfg`` as the tool reads it
    (:func:`~magail_sumo.sim.sumo_config.read_config`: never ``-c``; outputs, logs and ports
    of the file dropped), writing the three outputs into ``out``; cleaned additional files
    go into the folder ``private``.

    :raises SumoConfigError: the configuration cannot be used.
    :raises SumoBinaryMissing: no ``sumo`` binary.
    """
    inputs = read_config(sumocfg)
    copies = inputs.materialise(private) if private is not None and inputs.cleaned else {}
    opts = sumo_options(out, begin, end, seed, extra_args)
    over = {k[2:]: v for k, v in zip(opts[::2], opts[1::2])}
    over |= {"no-step-log": "true", "no-warnings": "true"}
    return [binary("sumo"), *inputs.args(over, copies)]


def _controlled(sumocfg: str, options: list[str], controller: str) -> None:
    """Worker: run ``sumocfg`` with ``options`` (:func:`sumo_options`) in a
    :class:`~magail_sumo.sim.session.SumoSession`, calling ``controller(api, time_s)`` before
    each step (``api``: the session's :attr:`~magail_sumo.sim.session.SumoSession.api`)."""
    mod, _, attr = controller.partition(":")
    fn = getattr(importlib.import_module(mod), attr)
    # every option comes from ``options``: none of the session's own (teleports, collisions)
    config = SessionConfig(step_length=None, seed=None, time_to_teleport=None,
                           collision_action=None, extra_args=options, subscribe=False)
    with SumoSession(sumocfg, config=config) as session:
        api = session.api
        while api.simulation.getMinExpectedNumber() > 0:
            fn(api, api.simulation.getTime())
            session.step()
            end = api.simulation.getEndTime()
            if end >= 0 and api.simulation.getTime() >= end:
                break


def _controlled_job(job: tuple[str, list[str], str]) -> None:
    _controlled(*job)


def run_sumo_outputs(sumocfg: str | Path, out_dir: str | Path, *, begin: float | None = None,
                     end: float | None = None, seed: int = 0, controller: str | None = None,
                     extra_args: Sequence[str] = (), timeout_s: float = 600) -> SumoRunSummary:
    """Run a scenario with tripinfo / edgeData / statistics outputs and summarise them.

    :param controller: ``"module:function"``; when given, ``function(api, time_s)`` is
        called before every step in a fresh worker process (:func:`magail_sumo.workers.run_one`)
        running a :class:`~magail_sumo.sim.session.SumoSession` (``api``: its TraCI-style
        domains, :attr:`~magail_sumo.sim.session.SumoSession.api`), a controlled run; else the
        ``sumo`` binary runs unchanged (SUMO default).
    :raises SumoRunError: SUMO fails or times out.
    """
    cfg, out = Path(sumocfg), Path(out_dir)
    if not cfg.is_file():
        raise SumoRunError(f"{cfg}: SUMO config not found")
    out.mkdir(parents=True, exist_ok=True)
    if controller is None:
        with tempfile.TemporaryDirectory(prefix="magail_sumo_inputs_") as private:
            try:
                cmd = sumo_command(cfg, out, begin, end, seed, extra_args, Path(private))
            except (SumoConfigError, SumoBinaryMissing) as exc:
                raise SumoRunError(str(exc)) from None
            try:
                res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s,
                                     stdin=subprocess.DEVNULL)
            except subprocess.TimeoutExpired:
                raise SumoRunError(f"{cfg}: SUMO timed out after {timeout_s:.0f} s") from None
            if res.returncode != 0:
                msg = " ".join((res.stderr or res.stdout).split())[-300:]
                raise SumoRunError(f"{cfg}: SUMO failed (exit {res.returncode}): {msg}")
    else:
        res = run_one(_controlled_job, (str(cfg), sumo_options(out, begin, end, seed, extra_args),
                                        controller), timeout_s=timeout_s)
        if res.kind == "timeout":
            raise SumoRunError(f"{cfg}: controlled SUMO run timed out after {timeout_s:.0f} s")
        if not res.ok:
            raise SumoRunError(f"{cfg}: controlled SUMO run failed: {res.reason}")
    return summarise(out)


def _trips(path: Path, completed: Collection[str]) -> list[tuple[float, float, float]]:
    """(duration, waitingTime, timeLoss) (s) of the trips of a tripinfo file that arrived: not
    ``vaporized``, or in ``completed``."""
    out = []
    try:
        for _, el in ET.iterparse(path):
            if el.tag == "tripinfo":
                a = el.attrib
                if not a.get("vaporized") or a.get("id") in completed:
                    try:
                        out.append((float(a["duration"]), float(a["waitingTime"]),
                                    float(a["timeLoss"])))
                    except (KeyError, ValueError):
                        raise SumoRunError(f"{path}: tripinfo {a.get('id')!r} lacks a numeric "
                                           "duration, waitingTime or timeLoss") from None
                el.clear()
    except ET.ParseError as exc:
        raise SumoRunError(f"{path}: not valid XML ({exc})") from None
    return out


def summarise(out_dir: str | Path, completed: Collection[str] = ()) -> SumoRunSummary:
    """Read the outputs of :func:`run_sumo_outputs` in ``out_dir``.

    :param completed: ids of vehicles a controller removed at the end of their trip (their
        tripinfo, marked ``vaporized``, counts as an arrival); other removed vehicles are left
        out (module doc).
    """
    import pandas as pd
    from sumolib.output import parse_fast

    o = _outputs(Path(out_dir))
    for path in o.values():
        if not path.is_file():
            raise SumoRunError(f"{path}: SUMO output missing")
    trips = pd.DataFrame(_trips(o["tripinfo"], set(completed)),
                         columns=["duration", "waiting", "loss"])
    speeds, w, duration = _edge_speeds(o["edgedata"])
    mean_speed = float(np.average(speeds, weights=w)) if w.sum() > 0 else float("nan")
    teleports = collisions = 0
    for tel in parse_fast(str(o["statistics"]), "teleports", ["total"]):
        teleports = int(tel.total)
    for safety in parse_fast(str(o["statistics"]), "safety", ["collisions"]):
        collisions = int(safety.collisions)
    n = len(trips)
    mean = lambda c: float(trips[c].mean()) if n else float("nan")  # noqa: E731
    return SumoRunSummary(n, mean("duration"), mean("waiting"), mean("loss"),
                          n * 3600.0 / duration if duration > 0 else float("nan"), mean_speed,
                          teleports, duration, collisions)


def _edge_speeds(path: Path) -> tuple[np.ndarray, np.ndarray, float]:
    """(mean speed of each edge and interval (m/s), its sampled seconds, the longest
    interval (s)) of an edgeData file."""
    from sumolib.output import parse_fast_nested

    speeds, weights = [], []
    duration = 0.0
    for interval, edge in parse_fast_nested(str(path), "interval", ["begin", "end"],
                                            "edge", ["sampledSeconds", "speed"]):
        duration = max(duration, float(interval.end) - float(interval.begin))
        speeds.append(float(edge.speed))
        weights.append(float(edge.sampledSeconds))
    return np.asarray(speeds, np.float64), np.asarray(weights, np.float64), duration


def _regular(path: Path) -> bool:
    """Whether ``path`` is a regular file (not a FIFO a reader would block on)."""
    try:
        regular_file(path)
        return True
    except InputFileError:
        return False


def run_distributions(out_dir: str | Path, completed: Collection[str] = ()) -> dict:
    """What the report draws of one run of :func:`run_sumo_outputs` in ``out_dir``:
    ``{"travel_time_s": durations of the arrived trips (as :func:`summarise` counts them),
    "edge_speed_mps": (speeds, sampled seconds) of the edgeData, "time_s", "running": the
    vehicles in the network at each step (empty without the summary file)}``; a missing or
    non-regular file gives empty arrays."""
    out = Path(out_dir)
    o = _outputs(out)
    trips = _trips(o["tripinfo"], set(completed)) if _regular(o["tripinfo"]) else []
    speeds, weights = (_edge_speeds(o["edgedata"])[:2] if _regular(o["edgedata"])
                       else (np.zeros(0), np.zeros(0)))
    t, running = [], []
    if _regular(out / SUMMARY_FILE):
        from sumolib.output import parse_fast

        for step in parse_fast(str(out / SUMMARY_FILE), "step", ["time", "running"]):
            t.append(float(step.time))
            running.append(float(step.running))
    return {"travel_time_s": np.asarray([d for d, _, _ in trips], np.float64),
            "edge_speed_mps": (speeds, weights),
            "time_s": np.asarray(t, np.float64), "running": np.asarray(running, np.float64)}


def compare_runs(runs: dict[str, SumoRunSummary]):
    """Runs side by side: a pandas DataFrame with one row per run (name index)."""
    import pandas as pd

    return pd.DataFrame({k: asdict(v) for k, v in runs.items()}).T
