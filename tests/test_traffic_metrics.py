"""Traffic metrics on real scenes (log replay and constructed rollouts) and SUMO city outputs."""

from __future__ import annotations

import os
import signal
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT
from magail_sumo.evaluation.realism import log_replay
from magail_sumo.evaluation.traffic import (
    METRICS, MetricInput, SumoRunError, compare_runs, compute_metrics, lanes, make_metric,
    run_sumo_outputs,
)
from magail_sumo.evaluation.traffic.distributions import histogram, js_divergence

COLOGNE = ROOT / "data" / "sumo" / "cologne8" / "cologne8.sumocfg"


@pytest.fixture(scope="module")
def replay(scene_637f):
    return MetricInput.build(scene_637f, log_replay(scene_637f, 4))


def _shifted(scene, dx: float):
    ro = log_replay(scene, 4)
    return replace(ro, x=ro.x + np.float32(dx))


def test_log_replay_matches_the_log(replay):
    m = compute_metrics(replay)
    assert set(m) == set(METRICS)
    assert m["ade"] == m["min_ade"] == m["fde"] == 0.0
    assert m["route_completion"] == pytest.approx(1.0)
    for k in ("speed_js", "acceleration_js", "jerk_js", "yaw_rate_js", "ttc_js",
              "nearest_object_distance_js"):
        assert m[k] == pytest.approx(0.0, abs=1e-12), k
    assert 0 <= m["collision_rate"] <= 1 and 0 <= m["hard_braking_rate"] <= 1


def test_constructed_shift(scene_637f):
    inp = MetricInput.build(scene_637f, _shifted(scene_637f, 1.0))
    m = compute_metrics(inp, ["ade", "min_ade", "fde", "speed_js"])
    assert m["ade"] == pytest.approx(1.0, abs=1e-3) and m["fde"] == pytest.approx(1.0, abs=1e-3)
    assert m["min_ade"] == pytest.approx(1.0, abs=1e-3)
    assert m["speed_js"] == pytest.approx(0.0, abs=1e-9)  # a shift keeps every speed
    far = MetricInput.build(scene_637f, _shifted(scene_637f, 200.0))
    assert make_metric("route_completion").compute(far) == 0.0
    assert make_metric("offroad_rate").compute(far) > make_metric("offroad_rate").compute(inp)


def test_hard_braking_constructed(scene_637f):
    ro = log_replay(scene_637f, 2)
    tr, cur = scene_637f.tracks, scene_637f.current_time_index
    inp0 = MetricInput.build(scene_637f, ro)
    veh = np.flatnonzero(inp0.is_vehicle & inp0.valid.all(1))[0]
    oid = inp0.jt.object_id[veh]
    a = int(np.flatnonzero(ro.object_id == oid)[0])
    t = np.arange(1, 81) * 0.1
    x = ro.x.copy()
    y = ro.y.copy()
    h = ro.heading.copy()
    r = int(np.flatnonzero(tr.id == oid)[0])
    s = 15.0 * t - 0.5 * 5.0 * np.minimum(t, 3.0) ** 2 - 15.0 * np.maximum(t - 3.0, 0) + \
        np.where(t > 3.0, 0.0, 0.0)  # 15 m/s braking at 5 m/s² to 0 within 3 s
    s = np.where(t > 3.0, 15.0 * 3.0 - 0.5 * 5.0 * 9.0, s)
    x[1, a] = tr.x[r, cur] + s
    y[1, a] = tr.y[r, cur]
    h[1, a] = 0.0
    inp = MetricInput.build(scene_637f, replace(ro, x=x, y=y, heading=h))
    acc = inp.feature("linear_acceleration")[2, veh]
    assert np.nanmin(acc) == pytest.approx(-5.0, abs=0.3)
    from magail_sumo.evaluation.traffic.events import HARD_BRAKE

    flags = (np.nan_to_num(inp.feature("linear_acceleration"), nan=0.0) < HARD_BRAKE)
    assert flags[2, veh].any() and not (flags[1, veh].any() and not flags[0, veh].any())


def test_js_divergence_properties():
    p = histogram(np.array([1.0, 1.0, 2.0]), "linear_speed")
    q = histogram(np.array([20.0, 21.0]), "linear_speed")
    assert js_divergence(p, p) == 0.0
    assert js_divergence(p, q) == pytest.approx(1.0)
    assert histogram(np.array([-5.0, 99.0]), "linear_speed")[[0, -1]].tolist() == [0.5, 0.5]


def test_lane_change_counting(replay, monkeypatch):
    n = len(replay.scene.roadmap.lanes)
    i, j = 0, 1
    seq = np.full(replay.x.shape, i)
    seq[:, :, 40:] = j  # every object moves from lane 0 to lane 1 at step 40
    seq[:, :, 20:25] = -1  # unmatched steps carry the last lane
    monkeypatch.setattr(lanes, "lane_sequence", lambda inp: seq)
    monkeypatch.setattr(lanes, "neighbour_pairs", lambda inp: np.array([i * n + j]))
    count = lanes.lane_changes(replay)
    want = replay.valid[:, 40:].any(1) & replay.valid[:, :40].any(1)  # across gaps too
    assert np.array_equal(count[1], want.astype(int))
    monkeypatch.setattr(lanes, "neighbour_pairs", lambda inp: np.zeros(0, np.int64))
    assert lanes.lane_changes(replay).sum() == 0  # a successor switch is no lane change


def _scaled(scene, k: float):
    """Log replay with every position scaled by ``k`` about the scene's centre: every
    horizontal velocity times ``k``."""
    ro = log_replay(scene, 3)
    cx, cy = np.float32(ro.x.mean()), np.float32(ro.y.mean())
    return replace(ro, x=cx + (ro.x - cx) * np.float32(k), y=cy + (ro.y - cy) * np.float32(k))


def test_speed_bias(scene_637f, replay):
    assert make_metric("speed_bias").unit == "m/s"
    assert make_metric("speed_bias").compute(replay) == pytest.approx(0.0, abs=1e-6)
    logged = make_metric("mean_speed").compute(replay)  # the log's mean speed on the mask
    assert logged > 1.0
    for k in (0.8, 1.1):
        inp = MetricInput.build(scene_637f, _scaled(scene_637f, k))
        bias = make_metric("speed_bias").compute(inp)
        assert bias == pytest.approx((k - 1.0) * logged, rel=0.02), k
        # all speeds finite here: the difference of the two means
        assert bias == pytest.approx(make_metric("mean_speed").compute(inp) - logged, abs=1e-4)
    # object-steps where the log has no speed do not count: a wild rollout there changes nothing
    m, lv = replay.mask("linear_speed"), replay.valid
    a = int(np.flatnonzero((~lv).any(1) & m.any(1))[0])  # an object the log loses a while
    t = int(np.flatnonzero(~lv[a])[0])  # a step the log has no state for
    ro = log_replay(scene_637f, 4)
    col = int(np.flatnonzero(ro.object_id == replay.jt.object_id[a])[0])
    x = ro.x.copy()
    x[:, col, t] += 50.0
    wild = MetricInput.build(scene_637f, replace(ro, x=x))
    hit = wild.mask("linear_speed")
    assert np.array_equal(hit, m)
    changed = np.isfinite(wild.feature("linear_speed")[1:, a]) & \
        (wild.feature("linear_speed")[1:, a] != replay.feature("linear_speed")[1:, a])
    assert changed.any() and not (changed & m[a][None]).any()
    assert make_metric("speed_bias").compute(wild) == pytest.approx(0.0, abs=1e-6)


def test_factory_and_units():
    with pytest.raises(KeyError, match="unknown traffic metric"):
        make_metric("nope")
    for name, cls in METRICS.items():
        assert cls.name == name and cls.unit and cls.description


@pytest.mark.sumo
def test_sumo_city_outputs(tmp_path):
    default = run_sumo_outputs(COLOGNE, tmp_path / "default", end=25400, seed=1)
    slow = run_sumo_outputs(COLOGNE, tmp_path / "slow", end=25400, seed=1,
                            controller="magail_sumo_test_controllers:slow_down",
                            extra_args=())
    assert default.arrived > 10 and default.duration_s == pytest.approx(200.0)
    assert default.travel_time_s > 0 and default.waiting_time_s >= 0
    assert default.throughput_veh_h == pytest.approx(default.arrived * 18.0)
    assert 0 < default.mean_edge_speed_mps < 20 and default.teleports >= 0
    assert slow.mean_edge_speed_mps < default.mean_edge_speed_mps
    table = compare_runs({"default": default, "controlled": slow})
    assert list(table.index) == ["default", "controlled"] and "teleports" in table.columns
    with pytest.raises(SumoRunError, match="not found"):
        run_sumo_outputs(tmp_path / "missing.sumocfg", tmp_path / "x")


@pytest.fixture(autouse=True)
def _controller_module(tmp_path, monkeypatch):
    """A controller module the spawned SUMO worker can import (via PYTHONPATH)."""
    mod = tmp_path / "magail_sumo_test_controllers.py"
    mod.write_text("def slow_down(ls, t):\n"
                   "    for v in ls.simulation.getDepartedIDList():\n"
                   "        ls.vehicle.setMaxSpeed(v, 4.0)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    yield Path(mod)


# ----------------------------------------------------------------- a controlled SUMO run that stops
SID = "850c48d8bbfa008f"  # the smallest bundled scene


def stopping_controller(libsumo, time_s: float) -> None:
    """A SUMO controller whose process stops itself after the first steps."""
    if time_s >= 0.5:
        os.kill(os.getpid(), signal.SIGSTOP)


@pytest.mark.sumo
def test_controlled_sumo_run_that_stops_times_out(tmp_path, bundled_networks):
    from magail_sumo.evaluation.traffic import sumo_outputs as so

    cfg = bundled_networks(SID) / SID / f"{SID}.sumocfg"
    clock = time.monotonic()
    with pytest.raises(so.SumoRunError, match="controlled SUMO run timed out after 8 s"):
        so.run_sumo_outputs(cfg, tmp_path / "o", controller=f"{__name__}:stopping_controller",
                            timeout_s=8)
    assert time.monotonic() - clock < 300  # generous: the stopped SUMO would never answer
