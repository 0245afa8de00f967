"""SUMO car-following against log replay and constant velocity: realism and event rates.

Runs ``magail-sumo evaluate --policy sumo --baselines logreplay,constvel`` and ``magail-sumo
report`` (the library functions the CLI uses) on the given scenes and prints, per scene and
method and as means over the scenes, the WOSAC realism meta-metric, the simulated collision and
off-road rates of the scored agents (``simulated_collision_rate`` / ``simulated_offroad_rate``
of the report's ``metrics.csv``: share of scored agents × rollouts with at least one event), the
number of scored agents (the SDC plus the tracks to predict; the SDC alone in a scene without
tracks to predict) and, as a less noisy figure, the report's ``collision_rate`` over all
simulated objects (same collision test) with their number. A scene whose map has no road edges
(the nuScenes pickles) has no off-road rate and no meta-metric (printed as nan: not comparable);
it counts in the collision means, and the meta-metric and off-road means are over the scenes
that have them (their number is printed). Issue 14's goals for ``sumo``: collision rate ≤ log
replay's + 0.05 and meta-metric ≥ 0.60 on scenes not used to tune it.

    python benchmarks/sumo_baseline.py data/womd/*.tfrecord [--rollouts 8] [--out DIR] [--json]
    python benchmarks/sumo_baseline.py SCENES --pedestrians [--networks DIR]   # SUMO persons

With ``--pedestrians`` the scenes are first converted with ``ConvertOptions.pedestrians``
(sidewalks, crossings; recorded pedestrians walk as SUMO persons that SUMO's drivers yield to)
into ``--networks DIR`` (default: a temporary folder); bundles already converted there with
those options are reused.
    python benchmarks/sumo_baseline.py --rescore DIR     # score an earlier run's rollouts again
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

METHODS = ("sumo", "logreplay", "constvel")
FIELDS = {"metametric": "meta", "simulated_collision_rate": "collision",
          "simulated_offroad_rate": "off-road", "collision_rate": "coll-all"}
COLLISION_MARGIN = 0.05
META_GOAL = 0.60


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", help="scene files (TFRecords, ScenarioNet pickles)")
    ap.add_argument("--rollouts", type=int, default=8)
    ap.add_argument("--out", type=Path, help="evaluation folder (default: a temporary one)")
    ap.add_argument("--networks", type=Path, help="converted bundles to reuse (evaluate --networks)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rescore", type=Path, metavar="DIR",
                    help="no rollouts: report an earlier run's evaluation folder again")
    ap.add_argument("--pedestrians", action="store_true",
                    help="convert with sidewalks and crossings first (into --networks)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if bool(args.scenes) == bool(args.rescore):
        ap.error("give scene files or --rescore DIR")
    errors: list[str] = []
    if args.pedestrians and not args.rescore:
        args.networks = pedestrian_networks(args.scenes, args.networks, errors)

    from magail_sumo.evaluation.realism.trajectories import evaluated_ids
    from magail_sumo.evaluation.report import build_report
    from magail_sumo.evaluation.runner import evaluate
    from magail_sumo.evaluation.submission import sim_agent_ids

    out = args.rescore or args.out or Path(tempfile.mkdtemp(prefix="sumo_baseline_"))
    if not args.rescore:
        errors += evaluate(args.scenes, "sumo", out, n_rollouts=args.rollouts,
                           baselines=["logreplay", "constvel"], seed=args.seed,
                           workers=args.workers, networks=args.networks).errors
    rep = build_report(out)
    n_rollouts = rep.scores.manifest.get("rollouts")
    for e in rep.errors:
        print(f"error: {e}", file=sys.stderr)
    with open(rep.metrics_csv, newline="") as fh:
        csv_rows = list(csv.DictReader(fh))
    scored = {sid: len(evaluated_ids(sc)) for sid, sc in rep.scores.scenes.items()}
    agents = {sid: len(sim_agent_ids(sc)) for sid, sc in rep.scores.scenes.items()}
    rows = [{"scenario_id": r["scenario_id"], "method": r["method"],
             "scored_agents": scored[r["scenario_id"]], "agents": agents[r["scenario_id"]],
             **{f: float(r[f]) for f in FIELDS}} for r in csv_rows]
    scenes = [s for s in scored if all(any(r["scenario_id"] == s and r["method"] == m
                                           for r in rows) for m in METHODS)]
    # per field, the scenes where every method has it (no meta-metric / off-road rate without
    # road edges): the means are over those
    having = {f: [s for s in scenes if all(np.isfinite(r[f]) for r in rows
                                           if r["scenario_id"] == s)] for f in FIELDS}
    means = {m: {f: float(np.mean([r[f] for r in rows if r["method"] == m
                                   and r["scenario_id"] in having[f]]))
                 if having[f] else float("nan") for f in FIELDS} for m in METHODS}
    goals = {}
    if having["simulated_collision_rate"]:
        goals["collision_le_logreplay_plus_0.05"] = bool(
            means["sumo"]["simulated_collision_rate"]
            <= means["logreplay"]["simulated_collision_rate"] + COLLISION_MARGIN)
    if having["metametric"]:
        goals["metametric_ge_0.60"] = bool(means["sumo"]["metametric"] >= META_GOAL)
    verdict = {k: "n/a" if k not in goals else "met" if goals[k] else "NOT met"
               for k in ("collision_le_logreplay_plus_0.05", "metametric_ge_0.60")}
    res = {"out": str(out), "rollouts": n_rollouts, "scenes_complete": scenes,
           "scenes_per_mean": {f: having[f] for f in FIELDS},
           "errors": errors + list(rep.errors), "rows": rows, "means": means, "goals": goals}
    if args.json:
        print(json.dumps(res, indent=2))
        return 0
    print(f"{n_rollouts} rollouts per scene; {len(scenes)} scene(s) with all methods "
          f"(means over those); evaluation in {out}")
    for f in ("metametric", "simulated_offroad_rate"):
        if len(having[f]) < len(scenes):
            print(f"{FIELDS[f]}: mean over the {len(having[f])} of those scene(s) that have it "
                  f"(nan: a map without road edges, not comparable)")
    print(f"{'scene':<22}{'method':<11}" + "".join(f"{v:>10}" for v in FIELDS.values())
          + f"{'scored':>8}{'all':>6}")
    for s in scored:
        for m in METHODS:
            for r in (r for r in rows if r["scenario_id"] == s and r["method"] == m):
                print(f"{s[:21]:<22}{m:<11}" + "".join(f"{r[f]:>10.4f}" for f in FIELDS)
                      + f"{r['scored_agents']:>8}{r['agents']:>6}")
    for m in METHODS:
        print(f"{'mean':<22}{m:<11}" + "".join(f"{means[m][f]:>10.4f}" for f in FIELDS)
              + f"{sum(scored[s] for s in scenes):>8}{sum(agents[s] for s in scenes):>6}")
    print(f"goals (sumo, means): collision ≤ logreplay + {COLLISION_MARGIN}: "
          f"{verdict['collision_le_logreplay_plus_0.05']}; meta-metric ≥ {META_GOAL}: "
          f"{verdict['metametric_ge_0.60']}")
    return 0


def pedestrian_networks(scenes: list[str], folder: Path | None, errors: list[str]) -> Path:
    """``folder`` (default: a new temporary one) holding the scenes' bundles converted with
    pedestrians (those already there with the same converter and options are kept)."""
    from converters.scene_files import iter_scenes
    from converters.sumo.batch import converted_before
    from converters.sumo.scenario import ConvertOptions, claim_networks_dir, convert_scene

    folder = folder or Path(tempfile.mkdtemp(prefix="sumo_baseline_networks_"))
    claim_networks_dir(folder)
    opts = ConvertOptions(pedestrians=True, baseline=False)
    for scene in iter_scenes(scenes):
        if converted_before(folder, scene.scenario_id, opts) is None:
            rep = convert_scene(scene, folder, opts)
            if rep.status != "ok":
                errors.append(rep.reason)
    return folder


if __name__ == "__main__":
    sys.exit(main())
