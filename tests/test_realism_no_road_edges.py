"""Realism scoring of a scene whose map has no road edges (the nuScenes ScenarioNet pickles):
every feature that does not need road edges is scored as usual, the road-edge fields and the
meta-metric are NaN."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from converters import load_scene
from magail_sumo.cli.main import main
from magail_sumo.evaluation.realism import METRIC_FIELDS, log_replay, scenario_metrics
from magail_sumo.sensors.road_edge import has_road_edges
from magail_sumo.evaluation.report.scoring import AGENT_FIELDS, score_pair
from magail_sumo.evaluation.submission import read_submission, write_submission

ROOT = Path(__file__).resolve().parents[1]
NUSC = ROOT / "data" / "scenarionet" / "sd_nuscenes_v1.0-mini_scene-0757.pkl"
WOMD = ROOT / "data" / "womd" / "637f20cafde22ff8.tfrecord"
CONSTVEL = ROOT / "data" / "wosac" / "constvel_637f20cafde22ff8.binproto"

#: Fields that need road edges (the meta-metric sums every likelihood).
EDGE_FIELDS = {"metametric", "distance_to_road_edge_likelihood",
               "offroad_indication_likelihood", "simulated_offroad_rate"}


@pytest.fixture(scope="module")
def nusc():
    return load_scene(NUSC)


def test_nuscenes_scene_scored_without_road_edges(nusc):
    """The real nuScenes scene (no road edges in its map) gets a report row: collision rates
    and every other likelihood present, road-edge fields, off-road rates and meta NaN."""
    assert not has_road_edges(nusc)
    res = score_pair(nusc, "logreplay", log_replay(nusc, 2))
    assert res.error is None
    row = res.row
    for f in EDGE_FIELDS | {"offroad_rate"}:
        assert math.isnan(row[f]), f
    for f in set(METRIC_FIELDS) - EDGE_FIELDS:
        assert math.isfinite(row[f]), f
    assert 0.0 <= row["simulated_collision_rate"] <= 1.0
    assert math.isfinite(row["collision_rate"]) and math.isfinite(row["hard_braking_rate"])
    assert res.agent_rows
    for a in res.agent_rows:
        assert math.isnan(a["offroad_rate"]) and math.isnan(a["distance_to_road_edge_likelihood"])
        assert math.isfinite(a["collision_rate"]) and math.isfinite(a["ade"])
        assert set(AGENT_FIELDS) <= set(a)


def test_womd_scene_without_road_edges_keeps_every_other_field():
    """The same WOMD rollouts scored with and without the map's road edges: the road-edge
    fields become NaN, every other field is bit-identical; with them every field is finite
    (the official values are checked in test_realism.py)."""
    scene = load_scene(WOMD)
    (ro,) = read_submission(CONSTVEL)
    full = scenario_metrics(scene, ro)
    bare = dataclasses.replace(scene, roadmap=dataclasses.replace(scene.roadmap, road_edges=()))
    part = scenario_metrics(bare, ro)
    assert all(math.isfinite(full[f]) for f in METRIC_FIELDS)
    for f in METRIC_FIELDS:
        if f in EDGE_FIELDS:
            assert math.isnan(part[f]), f
        else:
            assert part[f] == full[f], f


def test_realism_cli_reports_partial_fields(nusc, tmp_path, capsys):
    """``magail-sumo realism`` scores such a scene (exit 0) with NaN road-edge fields: "nan" in
    the table, null in --json, a note on stderr."""
    sub = tmp_path / "log.binproto"
    write_submission(sub, [log_replay(nusc, 32)])
    assert main(["realism", "--scenes", str(NUSC), "--submission", str(sub), "--json"]) == 0
    out, err = capsys.readouterr()
    row = json.loads(out.splitlines()[0])
    assert row["scenario_id"] == nusc.scenario_id
    assert all(row[f] is None for f in EDGE_FIELDS)
    assert isinstance(row["simulated_collision_rate"], float)
    assert "no road edges" in err and "metametric" in err
    assert main(["realism", "--scenes", str(NUSC), "--submission", str(sub)]) == 0
    table = capsys.readouterr().out
    meta = next(ln for ln in table.splitlines() if ln.startswith("metametric"))
    assert meta.split()[1] == "nan"
    assert np.isfinite(float(next(ln for ln in table.splitlines()
                                  if ln.startswith("simulated_collision_rate")).split()[1]))


def test_report_of_nuscenes_scene(tmp_path):
    """``evaluate`` + ``report`` on the nuScenes scene: a metrics.csv row per method with the
    collision rates and NaN meta-metric / off-road fields, no errors, and the report says why."""
    import csv

    from magail_sumo.evaluation.report import build_report
    from magail_sumo.evaluation.runner import evaluate

    res = evaluate([str(NUSC)], "constvel", tmp_path / "ev", n_rollouts=2,
                   baselines=["logreplay"], workers=1)
    assert not res.errors
    rep = build_report(tmp_path / "ev", workers=1)
    assert rep.errors == ()
    with open(rep.metrics_csv, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted(r["method"] for r in rows) == ["constvel", "logreplay"]
    for r in rows:
        assert math.isnan(float(r["metametric"])) and math.isnan(float(r["offroad_rate"]))
        assert math.isfinite(float(r["simulated_collision_rate"]))
        assert math.isfinite(float(r["collision_rate"]))
    assert "No road edges in the map of 1 scene(s) (scene-0757)" in rep.markdown.read_text()
