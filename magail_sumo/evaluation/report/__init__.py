"""Evaluation report of a ``magail-sumo evaluate`` folder: metric table against the baselines,
bar charts, sim-vs-log distributions, top-down trajectory overlays and the realism breakdown.

``build_report(DIR)`` writes ``DIR/report/report.html`` (self-contained: figures inlined, an
animated player per scene), ``report.md`` (with ``img/*.png``), ``metrics.csv`` (one row per
scene and method, every field), ``agents.csv`` (one row per scene, method and evaluated agent:
realism likelihoods, ADE / minADE, collision and off-road rates) and ``summary.csv`` (mean
over scenes per method). The report folder must be new, empty or written
by magail_sumo (:func:`~magail_sumo.outputs.claim_output_dir`); every file is written
atomically, inside it (:func:`~magail_sumo.outputs.inside`: a symbolic link out of it, such as
``DIR/report`` or ``report/img``, is refused) and image names from scenario ids go through
:func:`~magail_sumo.outputs.safe_name`.

A folder with city results (``DIR/city.json``, :mod:`magail_sumo.evaluation.city`) also gets a
"City scenarios (SUMO outputs)" table and ``city.csv``; a folder with only city results (no
recorded scenes) gets only those.
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path

from magail_sumo.errors import MagailSumoError
from magail_sumo.evaluation.city import (EVENTS as CITY_EVENTS, KINEMATICS_FILE, completed_ids,
                                         read_rows)
from magail_sumo.evaluation.bootstrap import paired_difference, verdict
from magail_sumo.evaluation.protocol import EvaluationError
from magail_sumo.inputs import read_json
from magail_sumo.evaluation.traffic import METRICS
from magail_sumo.evaluation.traffic.events import (ROAD_EDGES_DISAGREE,
                                                   ROAD_EDGES_DISAGREE_VEHICLES,
                                                   road_edges_disagree_with_log)
from magail_sumo.evaluation.traffic.sumo_outputs import run_distributions
from magail_sumo.outputs import (OutputError, atomic_write, claim_output_dir, inside, printable,
                                 safe_name)
from magail_sumo.agents.specs import unguarded
from magail_sumo.sensors.road_edge import has_road_edges
from magail_sumo.pretrained import is_pretrained_spec
from magail_sumo.workers import Progress, no_progress

from . import animation, figures
from .render import REALISM_FIELDS, Document
from .scores import SceneView, Scores
from .intervals import mean_ci, with_ci
from .scoring import AGENT_FIELDS, collect, method_intervals, method_means, scene_view

#: Traffic metrics in the main table, in order.
MAIN = ["ade", "min_ade", "fde", "collision_rate", "offroad_rate", "red_light_rate",
        "hard_braking_rate", "lane_changes", "route_completion", "mean_speed", "speed_bias",
        "nearest_object_distance", "ttc_below_1s", "speed_js", "acceleration_js", "jerk_js",
        "yaw_rate_js", "nearest_object_distance_js", "ttc_js"]


@dataclass(frozen=True)
class ReportFiles:
    html: Path
    markdown: Path
    metrics_csv: Path
    summary_csv: Path
    agents_csv: Path
    errors: tuple[str, ...]
    scores: Scores
    city_csv: Path | None = None


def _write_csv(path: Path, header: list[str], rows: list[list[object]]) -> None:
    with atomic_write(path, "w") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)


def _action_mode(man: dict) -> str:
    """How the checkpoint policy under test acted (``evaluate --deterministic`` or sampled,
    with its noise scale when not 1), as the manifest records it; empty for other policies and
    older manifests."""
    spec = man.get("policy_spec")
    spec = unguarded(spec) if isinstance(spec, str) else spec
    if "deterministic" not in man or not isinstance(spec, str):
        return ""
    if not is_pretrained_spec(spec):
        # lazy: only for a policy file (the policies import torch, seconds)
        from magail_sumo.policies import POLICY_LOADERS

        if Path(spec).suffix not in POLICY_LOADERS:
            return ""
    if man["deterministic"]:
        return " (deterministic actions)"
    scale = man.get("noise_scale")
    return (" (sampled actions)" if not isinstance(scale, (int, float)) or scale == 1
            else f" (sampled actions, noise scale {scale:g})")


def build_report(folder: str | Path, out: str | Path | None = None,
                 submissions: dict[str, list[str]] | None = None,
                 workers: int | None = None, progress: Progress = no_progress) -> ReportFiles:
    """Score ``folder`` (see :func:`~magail_sumo.evaluation.report.scoring.collect`, scored in
    ``workers`` processes, ``progress`` told as pairs are scored) and write the report into
    ``out`` (default ``folder/report``)."""
    folder = Path(folder)
    out = Path(out) if out else inside(folder, "report")
    owned = ["report.html", "report.md", "metrics.csv", "summary.csv", "agents.csv", "city.csv",
             "img"]
    claim_output_dir(out, "report", owned)
    for name in owned:  # a symbolic link out of the report folder: refused before scoring
        inside(out, name)
    sc = collect(folder, submissions, workers, progress)
    city_rows = _city_rows(folder, sc.errors)
    units = {n: METRICS[n].unit for n in METRICS}
    means = method_means(sc, ["metametric", *MAIN, *REALISM_FIELDS])
    cis = method_intervals(sc, ["metametric", *MAIN, *REALISM_FIELDS])
    man = sc.manifest
    doc = Document("magail_sumo evaluation report", out / "img")
    if sc.scenes or sc.methods or not city_rows:
        _scene_sections(doc, sc, means, cis, units, man)
    if city_rows:
        _city_section(doc, city_rows, man, folder, sc.errors)
    if sc.errors:
        doc.heading("Problems")
        doc.errors(sc.errors)
    html_path, md_path = inside(out, "report.html"), inside(out, "report.md")
    doc.write(html_path, md_path)
    all_fields = ["scenario_id", "method", "rollouts"] + list(METRICS) + \
        [f for f in sc.rows[0] if f not in METRICS and f not in ("scenario_id", "method",
                                                                  "rollouts")] if sc.rows else []
    metrics_csv, summary_csv = inside(out, "metrics.csv"), inside(out, "summary.csv")
    agents_csv = inside(out, "agents.csv")
    afields = ["scenario_id", "method", "object_id", "type", "sdc", *AGENT_FIELDS]
    _write_csv(agents_csv, afields, [[r[f] for f in afields] for r in sc.agent_rows])
    _write_csv(metrics_csv, all_fields, [[r.get(f) for f in all_fields] for r in sc.rows])
    sfields = ["metametric", *MAIN, *REALISM_FIELDS]
    _write_csv(summary_csv, ["method", *sfields, *(f"{f}_ci95" for f in sfields)],
               [[m, *(means[m][f] for f in sfields), *(cis[m][f] for f in sfields)]
                for m in sc.methods])
    city_csv = None
    if city_rows:
        city_csv = inside(out, "city.csv")
        _write_csv(city_csv, [*CITY_COLUMNS, *(f"terminations_{e}" for e in CITY_EVENTS)],
                   [[r[c] for c in CITY_COLUMNS]
                    + [r["terminations"].get(e, 0) for e in CITY_EVENTS] for r in city_rows])
    return ReportFiles(html_path, md_path, metrics_csv, summary_csv, agents_csv,
                       tuple(sc.errors), sc, city_csv)


#: what the log-replay row is (the report's note under the metrics table)
REFERENCE_NOTE = (
    "logreplay replays the recording itself: it is the reference the other methods are "
    "measured against, not a competitor. Its collision and off-road rates are not zero because "
    "they are the recording's own: boxes of recorded tracks that overlap (dense queues, "
    "merges, box sizes estimated by the perception system) and recorded positions the map "
    "puts off the road (driveways, parking lots, map polygons a metre off). A method is "
    "realistic as far as its figures approach these, not zero.")


def road_edges_disagree(sc: Scores) -> dict[str, float]:
    """The scenes whose road edges disagree with their log: scenario id -> the share of its
    recorded vehicles off the road edges (``log_offroad_rate`` of its rows), above
    :data:`~magail_sumo.evaluation.traffic.events.ROAD_EDGES_DISAGREE` and at least
    ``ROAD_EDGES_DISAGREE_VEHICLES`` of them."""
    out = {}
    for r in sc.rows:
        v, n = r.get("log_offroad_rate"), r.get("log_offroad_vehicles") or 0
        if isinstance(v, float) and road_edges_disagree_with_log(v, n):
            out[r["scenario_id"]] = v
    return out


def _offroad_apart(doc: Document, sc: Scores) -> None:
    """Off-road rates on the scenes whose road edges agree with their log and on those that
    do not, when there are any of the latter (the metrics table mixes both)."""
    bad = road_edges_disagree(sc)
    if not bad:
        return
    good = [s for s in sc.scenes if s not in bad]
    doc.para(f"Road edges that disagree with the log: in {len(bad)} of {len(sc.scenes)} "
             f"scene(s) the recording itself puts more than {ROAD_EDGES_DISAGREE:.0%} of the "
             f"vehicles (at least {ROAD_EDGES_DISAGREE_VEHICLES}) off the road edges (" + ", ".join(
                 f"{printable(s)} {v:.2f}" for s, v in sorted(bad.items())) + "), so off-road "
             "figures there say little. Off-road rate apart:")
    per = {(r["scenario_id"], r["method"]): r.get("offroad_rate") for r in sc.rows}
    doc.table(["method", f"agreeing scenes ({len(good)})", f"disagreeing scenes ({len(bad)})"],
              [[m, *(with_ci(*mean_ci(per.get((s, m)) for s in part))
                     for part in (good, sorted(bad)))] for m in sc.methods], "offroad-apart")


def _comparisons(doc: Document, sc: Scores) -> None:
    """Each pair of methods' meta-metric difference with its paired bootstrap interval over the
    scenes both scored (:mod:`magail_sumo.evaluation.bootstrap`); nothing with one method or
    fewer than two shared scenes."""
    sids = sorted(sc.scenes)
    per = {(r["scenario_id"], r["method"]): r["metametric"] for r in sc.rows}
    values = {m: [per.get((s, m), float("nan")) for s in sids] for m in sc.methods}
    rows = []
    for i, a in enumerate(sc.methods):
        for b in sc.methods[i + 1:]:
            shared = sum(math.isfinite(x) and math.isfinite(y)
                         for x, y in zip(values[a], values[b]))
            if shared < 2:
                continue
            d = paired_difference(values[a], values[b])
            rows.append([f"{a} − {b}", shared, f"{d.mean:+.4f}", f"[{d.lo:+.4f}, {d.hi:+.4f}]",
                         verdict(d, a, b)])
    if not rows:
        return
    doc.para("Meta-metric differences, paired on the scenes:")
    doc.table(["methods", "scenes", "difference", "95 % interval", "verdict"], rows,
              "comparisons")
    doc.note("95 % bootstrap interval of the difference of the mean meta-metric (10,000 "
             "resamples of the scenes both methods scored, the same scenes for both); a method "
             "is called better only where the interval excludes 0.")


def _scene_sections(doc: Document, sc: Scores, means: dict, cis: dict, units: dict,
                    man: dict) -> None:
    """The recorded scenes' sections: metrics, realism, figures, per-agent rows, fixes."""
    doc.para(f"Scenes: {len(sc.scenes)} · methods: {', '.join(sc.methods) or 'none'} · "
             f"rollouts: {man.get('rollouts')} (WOSAC: 32) × {man.get('steps', 80)} steps "
             f"(8 s) after the current step · seed {man.get('seed')} · policy under test: "
             f"{man.get('policy')}{_action_mode(man)}")
    doc.heading("Metrics against the baselines (mean over scenes)")
    header = ["method", "metametric"] + MAIN
    doc.table(header, [[m, *(with_ci(means[m][f], cis[m][f]) for f in ["metametric", *MAIN])]
                       for m in sc.methods], "metrics")
    doc.note(f"mean ± half-width of its 95 % confidence interval over the {len(sc.scenes)} "
             "scene(s) (Student's t; no interval with one scene). The rollouts of a scene are "
             "seeded: a second evaluation seed gives a second sample of the same scenes.")
    if "logreplay" in sc.methods:
        doc.note(REFERENCE_NOTE)
    _comparisons(doc, sc)
    _offroad_apart(doc, sc)
    doc.table(["metric", "unit", "definition"],
              [[n, units[n], METRICS[n].description] for n in MAIN], "units")
    if sc.methods:
        doc.image(figures.bar_chart(means, ["metametric", "ade", "collision_rate",
                                            "offroad_rate", "hard_braking_rate",
                                            "route_completion", "speed_js", "ttc_js"],
                                    {**units, "metametric": "WOSAC"}, "Methods compared",
                                    cis),
                  "bars", "bar charts of the main metrics per method")
    doc.heading("Realism (WOSAC 2025) breakdown")
    bare = [printable(s) for s in sorted(sc.scenes) if not has_road_edges(sc.scenes[s])]
    if bare:
        doc.para(f"No road edges in the map of {len(bare)} scene(s) ({', '.join(bare)}): their "
                 "distance-to-road-edge and off-road fields and their meta-metric are NaN (not "
                 "comparable); the means of those fields are over the other scenes.")
    doc.table(["method", "metametric"] + [f.replace("_likelihood", "") for f in REALISM_FIELDS],
              [[m, *(with_ci(means[m][f], cis[m][f]) for f in ["metametric", *REALISM_FIELDS])]
               for m in sc.methods], "realism")
    doc.note("Each field is the likelihood of the logged values under the method's rollouts "
             "(the WOSAC 2025 definitions; higher is better), mean ± 95 % interval over "
             "scenes.")
    sids = sorted(sc.scenes)
    per = {(r["scenario_id"], r["method"]): r for r in sc.rows}
    doc.para("Meta-metric per scene:")
    doc.table(["method"] + [printable(s) for s in sids], [[m, *(per[(s, m)]["metametric"] if (s, m) in per
                                         else float("nan") for s in sids)]
                                  for m in sc.methods], "per-scene")
    if sc.counts:
        doc.heading("Simulated vs logged distributions")
        doc.image(figures.distributions(sc, [("linear_speed", "speed (m/s)"),
                                             ("linear_acceleration", "acceleration (m/s²)"),
                                             ("time_to_collision", "time to collision (s)")]),
                  "distributions", "speed, acceleration and TTC distributions, log vs methods")
        doc.heading("Trajectories")
        views = {sid: _view(sc, sid) for sid in sids
                 if any((sid, m) in sc.rollouts for m in sc.methods)}
        for sid, view in views.items():
            doc.image(view.trajectories_png, f"traj_{safe_name(sid)}",
                      f"top-down trajectories of scene {printable(sid)}")
        doc.heading("Animated scenes")
        doc.para("Log (left) vs the first rollout of each method, 10 Hz from the current step; "
                 "play / pause, or drag the slider.")
        for sid, view in views.items():
            doc.heading(printable(sid), 3)
            doc.raw(view.animation_html, "(animated view: see report.html)")
        doc.css.append(animation.CSS)
        doc.scripts.append(animation.SCRIPT)
    if sc.agent_rows:
        doc.heading("Realism per agent")
        doc.para("Per evaluated agent (the SDC and the tracks to predict): each realism "
                 "feature's likelihood, ADE / minADE over rollouts (m) and the share of "
                 "rollouts in which it collides / goes off-road.")
        order = {m: k for k, m in enumerate(sc.methods)}
        arows = sorted(sc.agent_rows, key=lambda r: (r["scenario_id"], r["object_id"],
                                                     order.get(r["method"], 0)))
        short = [f.replace("_likelihood", "") for f in AGENT_FIELDS]
        doc.table(["scene", "agent", "type", "method", *short],
                  [[printable(r["scenario_id"], 40), f"{r['object_id']}{' (SDC)' if r['sdc'] else ''}",
                    r["type"], r["method"], *(r[f] for f in AGENT_FIELDS)] for r in arows],
                  "agents")
    fixes = [f for f in man.get("action_fixes", []) if isinstance(f, dict)]
    if fixes:
        doc.heading("Policy actions fixed up by the env")
        doc.para("Agent-steps for which the policy gave no action (the agent coasted: zero "
                 "acceleration and steering), actions for agents not in the scene (ignored), "
                 "and non-finite or out-of-range actions (replaced by 0 / clipped to [-1, 1]).")
        doc.table(["scene", "method", "missing", "unknown", "non-finite", "clipped"],
                  [[printable(str(f.get("scenario_id")), 40), f.get("method"),
                    int(f.get("missing", 0)), int(f.get("unknown", 0)),
                    max(0, int(f.get("nonfinite", 0)) - int(f.get("missing", 0))),
                    int(f.get("clipped", 0))]
                   for f in fixes], "action-fixes")


def _view(sc: Scores, sid: str) -> SceneView:
    """The scene's trajectory figure and animation: the scoring worker's when it drew the
    methods this report shows for the scene, else drawn here."""
    view = sc.views.get(sid)
    if view is not None and view.methods == tuple(m for m in sc.methods
                                                  if (sid, m) in sc.rollouts):
        return view
    return scene_view(sc, sid)


#: ``city.json`` fields in the city table and ``city.csv`` (then the terminations per event)
CITY_COLUMNS = ["scenario", "method", "begin_s", "end_s", "arrived", "travel_time_s",
                "waiting_time_s", "time_loss_s", "throughput_veh_h", "mean_edge_speed_mps",
                "teleports", "collisions", "agents", "agent_steps", "removed", "peak_agents",
                "speed_js_humans", "accel_js_humans"]


def _city_rows(folder: Path, errors: list[str]) -> list[dict]:
    """The folder's city rows (:func:`~magail_sumo.evaluation.city.read_rows`); a bad
    ``city.json`` is one error line and no rows."""
    try:
        return read_rows(folder)[0]
    except MagailSumoError as exc:
        errors.append(" ".join(str(exc).split()))
        return []


def _kinematics(folder: Path, scenario: str, errors: list[str]) -> dict | None:
    """The scenario's ``kinematics.json`` (None when there is none); unreadable: one error
    line and None."""
    try:
        path = inside(folder, "city", safe_name(scenario), KINEMATICS_FILE)
        if not os.path.lexists(path):
            return None
        kin = read_json(path, expected="a kinematics.json")
        if not isinstance(kin, dict) or not isinstance(kin.get("bins"), dict):
            raise EvaluationError(f"{path}: expected an object with bins")
        return kin
    except (MagailSumoError, OutputError) as exc:
        errors.append(" ".join(str(exc).split()))
        return None


def _count(v: float | int) -> int | float:
    """A count for a table cell (NaN stays NaN: shown as n/a)."""
    return int(v) if math.isfinite(v) else float("nan")


def _demand(city: dict) -> str:
    """The window's demand scale in words (nothing when the scenario's own)."""
    scale = city.get("demand_scale", 1.0)
    return "" if scale in (1, 1.0, None) else f", its demand scaled by {scale:g} (SUMO's --scale)"


def _city_section(doc: Document, rows: list[dict], man: dict, folder: Path,
                  errors: list[str]) -> None:
    """The "City scenarios (SUMO outputs)" table: per scenario, each method's SUMO figures;
    then per scenario a figure of the methods' runs (:func:`.figures.city_figure`) and one of
    their drivers' speeds and accelerations against recorded humans
    (:func:`.figures.kinematics_figure`, when the run measured them)."""
    city = man.get("city") if isinstance(man.get("city"), dict) else {}
    policies = ", ".join(dict.fromkeys(printable(r["method"], 40) for r in rows
                                       if r["method"] != "sumo"))
    doc.heading("City scenarios (SUMO outputs)")
    doc.para(f"The policy ({policies}) drives up to {city.get('max_agents', '?')} vehicles "
             "of a whole SUMO city at once (the rest is SUMO traffic); sumo: SUMO's default "
             "drivers only. Both runs start from the "
             f"same state after a {city.get('warmup_s', '?')} s warm-up and cover the same "
             f"window (SUMO time of day){_demand(city)}, with the same seed and SUMO settings "
             "(0.1 s steps, teleporting off). Trip figures are means over the trips that "
             "ended in the window (from tripinfo; agents taken out by a collision, off-road or "
             "red-light event count as removed, not arrived); mean speed from edgeData; "
             "teleports and "
             "collisions from SUMO's statistics; agent collisions, off-road, red light and "
             "destination are the env's events ending agents. Speed / acceleration JS: "
             "Jensen-Shannon divergence (bits) of the drivers' speed and 1-s acceleration "
             "distributions from recorded humans' (evaluate --city-humans); for sumo, the "
             "cars SUMO drove around the agents in the policy's run.")
    header = ["scenario", "method", "window (s)", "arrived", "travel time (s)",
              "waiting time (s)", "time loss (s)", "throughput (veh/h)", "mean speed (m/s)",
              "teleports", "collisions", "agents", "agent-steps", "removed", "peak agents",
              *(f"agent {e.replace('_', ' ')}" for e in CITY_EVENTS), "speed JS",
              "acceleration JS"]
    body = []
    for r in sorted(rows, key=lambda r: (r["scenario"], r["method"] == "sumo", r["method"])):
        mine = r["method"] != "sumo"  # the policy's own counts
        own = [_count(r[f]) for f in ("agents", "agent_steps", "removed", "peak_agents")] + \
            [_count(r["terminations"].get(e, 0)) for e in CITY_EVENTS]
        body.append([printable(r["scenario"], 40), printable(r["method"], 40),
                     "-".join(f"{r[f]:.1f}" if math.isfinite(r[f]) else "n/a"
                              for f in ("begin_s", "end_s")),
                     _count(r["arrived"]), r["travel_time_s"], r["waiting_time_s"],
                     r["time_loss_s"], r["throughput_veh_h"], r["mean_edge_speed_mps"],
                     _count(r["teleports"]), _count(r["collisions"]),
                     *(own if mine else [""] * len(own)), r["speed_js_humans"],
                     r["accel_js_humans"]])
    doc.table(header, body, "city")
    for scenario in dict.fromkeys(r["scenario"] for r in rows):
        runs = {}
        for r in rows:
            if r["scenario"] != scenario:
                continue
            try:
                d = inside(folder, "city", safe_name(scenario), safe_name(r["method"]))
            except OutputError:
                continue  # a link out of the folder: nothing of it is read
            runs[r["method"]] = run_distributions(d, completed_ids(d))
        if any(v["travel_time_s"].size or v["time_s"].size for v in runs.values()):
            doc.image(figures.city_figure(runs, scenario), f"city_{safe_name(scenario)}",
                      f"vehicles over time, travel times and speeds of city {scenario}")
        kin = _kinematics(folder, scenario, errors)
        if kin is not None:
            doc.image(figures.kinematics_figure(kin, scenario),
                      f"city_{safe_name(scenario)}_kinematics",
                      f"speed and acceleration of city {scenario}'s drivers against recorded "
                      "humans")
