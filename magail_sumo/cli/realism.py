"""``magail-sumo realism``: WOSAC 2025 realism metrics of a sim-agents submission."""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

from converters.scene_files import iter_scene_records
from magail_sumo.evaluation.realism import METRIC_FIELDS, aggregate_metrics, scenario_metrics
from magail_sumo.sensors.road_edge import has_road_edges
from magail_sumo.evaluation.submission import SubmissionError, iter_submission
from magail_sumo.outputs import printable


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("realism", help="score a sim-agents submission (WOSAC 2025 realism)",
                       description="Compute the Waymo Open Sim Agents Challenge 2025 realism "
                                   "metrics of a SimAgentsChallengeSubmission against the "
                                   "recorded scenes. Bad scenarios are reported on stderr and "
                                   "the others are still scored. A scene whose map has no road "
                                   "edges is scored without them: its road-edge fields and "
                                   "meta-metric are NaN (null in --json), noted on stderr.")
    p.add_argument("--scenes", nargs="+", required=True, metavar="FILE",
                   help="scene files (WOMD TFRecords, ScenarioNet pickles or folders)")
    p.add_argument("--submission", nargs="+", required=True, metavar="FILE.binproto",
                   help="submission file(s) or shards")
    p.add_argument("--json", action="store_true",
                   help="one JSON object per scene (scenario_id plus the official field names; "
                        "null for NaN)")
    p.set_defaults(func=run)


#: Fields a scene whose map has no road edges gets as NaN (the meta-metric sums them all).
ROAD_EDGE_FIELDS = ("metametric", "distance_to_road_edge_likelihood",
                    "offroad_indication_likelihood", "simulated_offroad_rate")


def json_row(row: dict[str, Any]) -> dict[str, Any]:
    """``row`` with NaN fields as None (JSON ``null``: standard JSON has no NaN)."""
    return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in row.items()}


def format_table(rows: list[dict[str, Any]]) -> str:
    """Fields as rows, scenes as columns (plus their mean when there are several)."""
    cols = [r["scenario_id"] for r in rows]
    vals = [[r[k] for r in rows] for k in METRIC_FIELDS]
    if len(rows) > 1:
        cols.append("mean")
        mean = aggregate_metrics(rows)
        for v, k in zip(vals, METRIC_FIELDS):
            v.append(mean[k])
    width = max(16, *(len(c) for c in cols))
    name_w = max(len(k) for k in METRIC_FIELDS)
    lines = [f"{'field':<{name_w}}  " + "  ".join(f"{c:>{width}}" for c in cols)]
    for k, v in zip(METRIC_FIELDS, vals):
        lines.append(f"{k:<{name_w}}  " + "  ".join(f"{x:>{width}.6f}" for x in v))
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    scenes = {}
    failed = 0
    for path in args.scenes:
        for rec in iter_scene_records(path):
            if rec.error is not None:
                print(f"error: {rec.error}", file=sys.stderr)
                failed += 1
            else:
                scenes[rec.scene.scenario_id] = rec.scene  # type: ignore[union-attr]
    rows: list[dict[str, Any]] = []
    seen = set()
    for rec in iter_submission(args.submission):
        try:
            if rec.error is not None:
                raise rec.error
            ro = rec.rollouts
            assert ro is not None
            if ro.scenario_id in seen:
                raise SubmissionError(ro.scenario_id, "given twice in the submission")
            seen.add(ro.scenario_id)
            if ro.scenario_id not in scenes:
                raise SubmissionError(ro.scenario_id, "no such scene among --scenes")
            row = {"scenario_id": ro.scenario_id,
                   **scenario_metrics(scenes[ro.scenario_id], ro)}
        except SubmissionError as exc:
            print(f"error: {exc}", file=sys.stderr)
            failed += 1
            continue
        except ValueError as exc:  # a scene the metrics cannot use
            print(f"error: scenario {rec.scenario_id}: {exc}", file=sys.stderr)
            failed += 1
            continue
        if not has_road_edges(scenes[ro.scenario_id]):
            print(f"note: scenario {printable(ro.scenario_id)}: the map has no road edges: "
                  f"{', '.join(ROAD_EDGE_FIELDS)} are NaN (not comparable)", file=sys.stderr)
        rows.append(row)
        if args.json:
            print(json.dumps(json_row(row)), flush=True)
    for sid in sorted(scenes.keys() - seen):
        print(f"error: scenario {sid}: no rollouts in the submission", file=sys.stderr)
        failed += 1
    if rows and not args.json:
        print(format_table(rows))
    if failed:
        print(f"scored {len(rows)} scenario(s); {failed} problem(s) reported above",
              file=sys.stderr)
    return 1 if failed else 0
