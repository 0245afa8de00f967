"""``magail-sumo inspect``: summarise recorded scenes (WOMD TFRecords, ScenarioNet pickles)."""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from typing import Any

from converters.scene_files import iter_scene_records
from magail_sumo.cli.progress import progress
from magail_sumo.outputs import printable
from magail_sumo.scene.signal_sanity import checked_signal_sanity, format_signal_sanity


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("inspect", help="print what recorded scene files contain",
                       description="Summarise every scene of WOMD TFRecord files/shards, ScenarioNet "
                                   "pickles or ScenarioNet dataset folders.")
    p.add_argument("files", nargs="+", metavar="FILE", help="scene files")
    p.add_argument("--json", action="store_true", help="one JSON object per scene on stdout")
    p.add_argument("--keep-synthetic", action="store_true",
                   help="keep tracks a source marks as generated, not recorded (ScenarioNet "
                        "metadata.selected_adv_id: safety-critical scenes' adversaries); "
                        "dropped by default, as everywhere human driving is used")
    p.add_argument("--skip-bad", action="store_true",
                   help="report unreadable records and go on (default: stop at the first)")
    p.set_defaults(func=run)


def format_text(summary: dict[str, Any], duration: float) -> str:
    tb = summary["tracks_by_type"]
    mf = summary["map_features"]
    return "\n".join([
        summary["scenario_id"],
        f"  steps             {summary['num_steps']} ({duration:.1f} s)",
        f"  tracks            {sum(tb.values())}: " + ", ".join(f"{v} {k}" for k, v in tb.items()),
        f"  valid states      {summary['valid_states']}",
        f"  map features      {sum(mf.values())}: " + ", ".join(f"{v} {k}" for k, v in mf.items()),
        f"  signal states     {summary['signal_states']}",
        *([f"  signal sanity     {format_signal_sanity(summary['signal_sanity'])}"]
          if "signal_sanity" in summary else []),
        f"  sdc track index   {summary['sdc_track_index']}",
        f"  tracks to predict {summary['tracks_to_predict']}",
        *format_data_quality(summary.get("data_quality")),
    ])


#: dropped references listed one per line in the text output; the rest are counted
MAX_LISTED = 10


def format_data_quality(dq: dict[str, Any] | None) -> list[str]:
    """Text lines of a scene's ``data_quality`` record (none for a clean scene)."""
    if not dq:
        return []
    lines = []
    dropped = dq.get("dropped_references", [])
    if dropped:
        lines.append(f"  dropped refs      {len(dropped)} (ids not in the map; the scene is kept)")
        for r in dropped[:MAX_LISTED]:
            owner = f"feature {r['feature_id']}" if r["feature_id"] >= 0 else "scene"
            lines.append(f"    {owner}: {r['field']} -> {printable(str(r['missing_id']), 60)}")
        if len(dropped) > MAX_LISTED:
            lines.append(f"    ... and {len(dropped) - MAX_LISTED} more (--json lists all)")
    inferred = dq.get("inferred_connectivity", {})
    if inferred.get("successors") or inferred.get("neighbors"):
        lines.append(f"  inferred lanes    {inferred.get('successors', 0)} successor and "
                     f"{inferred.get('neighbors', 0)} neighbour links (source has none)")
    lines.extend(f"  note              {printable(str(n), 200)}" for n in dq.get("notes", []))
    return lines


def run(args: argparse.Namespace) -> int:
    read = 0
    skipped: Counter[str] = Counter()
    many = len(args.files) > 1
    records = (rec for path in progress(args.files, desc="files", unit="file", enabled=many)
               for rec in iter_scene_records(path, args.keep_synthetic))
    for rec in progress(records, desc="scenes", unit="scene"):
        if rec.error is not None:
            print(f"error: {rec.error}", file=sys.stderr)
            if not args.skip_bad:
                return 1
            skipped[rec.error.reason] += 1
            continue
        scene = rec.scene
        assert scene is not None
        try:
            summary = scene.summary()
            summary["signal_sanity"] = checked_signal_sanity(scene)
        except Exception as exc:  # noqa: BLE001 - one scene's failure, not the batch's
            reason = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
            print(f"error: {rec.path}: record {rec.index}: scene {scene.scenario_id}: {reason}",
                  file=sys.stderr)
            if not args.skip_bad:
                return 1
            skipped[reason] += 1
            continue
        if args.json:
            print(json.dumps(summary), flush=True)
        else:
            print(format_text(summary, scene.duration), flush=True)
        read += 1
    if skipped or many:
        why = "; ".join(f"{n} × {reason}" for reason, n in skipped.most_common())
        print(f"read {read} scene(s) from {len(args.files)} file(s); skipped {sum(skipped.values())}"
              + (f" ({why})" if why else ""), file=sys.stderr)
    return 0 if read or not skipped else 1
