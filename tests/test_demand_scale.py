"""A denser city from the same scenario (``demand_scale``: SUMO's ``--scale``) in the city env,
its warm-up and the evaluation's SUMO run (issue 32: neither held-out city's demand has 200 cars
on the road at once)."""

from __future__ import annotations

import pytest

from conftest import ROOT

COLOGNE8 = ROOT / "data" / "sumo" / "cologne8" / "cologne8.sumocfg"


def _vehicles_after_warmup(scale: float) -> tuple[int, int]:
    from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv

    env = SumoCityEnv(COLOGNE8, CityEnvConfig(action_layout="accel_offset", warmup_s=300,
                                              max_agents=5, max_steps=10,
                                              demand_scale=scale))
    try:
        env.reset(seed=0)
        api = env._session.api
        return api.vehicle.getIDCount(), api.simulation.getLoadedNumber()
    finally:
        env.close()


@pytest.mark.sumo
def test_scaled_demand_fills_the_city():
    """After the same 300-s warm-up, twice the demand puts clearly more vehicles on cologne8's
    roads than its own, and half of it fewer."""
    base, _ = _vehicles_after_warmup(1.0)
    dense, _ = _vehicles_after_warmup(2.0)
    sparse, _ = _vehicles_after_warmup(0.5)
    assert base >= 30
    assert dense >= 1.5 * base and sparse <= 0.7 * base


@pytest.mark.sumo
def test_evaluation_runs_sumo_on_the_same_scaled_demand(tmp_path):
    """Both runs of a city evaluation see the scaled demand: SUMO's drivers complete more trips
    in the window than on the scenario's own demand, and the manifest records the scale."""
    import json

    from magail_sumo.evaluation.city import CitySettings, evaluate_city

    trips = {}
    for scale in (1.0, 2.0):
        st = CitySettings(steps=600, warmup_s=300, max_agents=20, demand_scale=scale,
                          timeout_s=None)
        res = evaluate_city("idm", [COLOGNE8], tmp_path / f"x{scale:g}", st)
        assert not res.errors
        trips[scale] = next(r for r in res.rows if r["method"] == "sumo")["arrived"]
        man = json.loads((tmp_path / f"x{scale:g}" / "manifest.json").read_text())
        assert man["city"]["demand_scale"] == scale
    assert trips[2.0] > 1.3 * trips[1.0]


def test_a_scale_that_is_not_positive_is_refused():
    from magail_sumo.env.city_env import CityEnvConfig
    from magail_sumo.evaluation.city import CitySettings
    from magail_sumo.evaluation.protocol import EvaluationError

    with pytest.raises(EvaluationError, match="--city-demand-scale must be > 0"):
        CitySettings(demand_scale=0.0)
    with pytest.raises(ValueError, match="demand_scale must be > 0"):
        CityEnvConfig(demand_scale=-1.0)


def test_the_report_says_when_the_demand_was_scaled():
    from magail_sumo.evaluation.report import _demand

    assert _demand({}) == "" and _demand({"demand_scale": 1.0}) == ""
    assert "scaled by 1.2 (SUMO's --scale)" in _demand({"demand_scale": 1.2})


@pytest.mark.sumo
def test_replay_watches_the_denser_city(tmp_path, capsys):
    """``replay --city-demand-scale 2`` records a city with clearly more vehicles in it."""
    import xml.etree.ElementTree as ET

    from magail_sumo.cli.main import main as cli

    seen = {}
    for scale in ("1", "2"):
        fcd = tmp_path / f"x{scale}" / "city.fcd.xml"
        fcd.parent.mkdir()
        assert cli(["replay", str(COLOGNE8.parent), "--policy", "idm", "--steps", "20",
                    "--city-warmup-s", "300", "--city-demand-scale", scale,
                    "--fcd", str(fcd)]) == 0
        seen[scale] = {v.get("id") for v in ET.parse(fcd).getroot().iter("vehicle")}
    capsys.readouterr()
    assert len(seen["2"]) >= 1.5 * len(seen["1"]) >= 45
