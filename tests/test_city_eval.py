"""evaluate --city: a policy on a real SUMO city (Cologne cut-out) against SUMO's default
drivers over the same window, from SUMO's outputs; the report's city table."""

from __future__ import annotations

import json
from pathlib import Path
import math
import shutil
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR
from magail_sumo.cli.main import main
from magail_sumo.evaluation import storage
from magail_sumo.evaluation.city import ROW_FIELDS
from magail_sumo.evaluation.traffic import summarise

CFG = ROOT / "data" / "sumo" / "cologne8" / "cologne8.sumocfg"
STEPS, WARMUP, SEED = 200, 60, 3
HUMANS = "637f20cafde22ff8"


class _Coast:
    """A pluggable policy: hold speed, no steering (agents on curves leave the road)."""

    def act(self, observations):
        return {a: np.zeros(2, np.float32) for a in observations}


def coast(seed: int) -> _Coast:
    return _Coast()


@pytest.fixture(scope="module")
def humans(tmp_path_factory, bundled_networks):
    """Expert data of the recorded humans of one bundled real scene."""
    out = tmp_path_factory.mktemp("humans") / "expert"
    assert main(["expert", str(WOMD_DIR / f"{HUMANS}.tfrecord"), "--out", str(out),
                 "--networks", str(bundled_networks(HUMANS))]) == 0
    return out


@pytest.fixture(scope="module")
def city(tmp_path_factory, humans):
    out = tmp_path_factory.mktemp("city")
    rc = main(["evaluate", "--policy", f"{__name__}:coast", "--city", str(CFG),
               "--city-steps", str(STEPS), "--city-warmup-s", str(WARMUP),
               "--city-max-agents", "6", "--seed", str(SEED), "--fcd-rollouts", "1",
               "--city-humans", str(humans), "--out", str(out)])
    assert rc == 0
    assert main(["report", str(out), "--workers", "1"]) == 0
    return out


@pytest.mark.sumo
def test_city_run_fcd_replays_in_sumo(city, tmp_path):
    """``--fcd-rollouts`` records the city run: FCD and a .sumocfg that plain SUMO runs (the
    agents and SUMO's vehicles of the window, on the city's network)."""
    import subprocess

    from magail_sumo.sim.binaries import binary

    man = json.loads((city / "manifest.json").read_text())
    (entry,) = man["city"]["scenarios"]
    fcd = Path(entry["fcd"])
    assert fcd.is_file() and fcd.parent == city / "city" / "cologne8" / "coast" / "fcd"
    cfg = fcd.with_name("cologne8.sumocfg")
    from magail_sumo.sim.fcd import KIND_COLORS

    types = fcd.with_name("cologne8.types.add.xml").read_text()  # colour: who drove it
    assert KIND_COLORS["agent"] in types and KIND_COLORS["sumo"] in types
    res = subprocess.run([binary("sumo"), "-c", str(cfg), "--end", "5", "--no-step-log",
                          "--fcd-output", str(tmp_path / "back.xml")],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-500:]


@pytest.mark.sumo
def test_city_training_episodes_are_recorded_with_fcd_dir(tmp_path):
    """``env.fcd_dir`` reaches city episodes (it was silently ignored): episode 0 of each env
    is written when it ends."""
    from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv
    from magail_sumo.env.config import EnvConfig

    cfg = CityEnvConfig.from_env(EnvConfig(fcd_dir=str(tmp_path / "fcd"), fcd_every=2),
                                 max_agents=4, control_fraction=1.0, warmup_s=0, max_steps=20)
    env = SumoCityEnv(CFG, cfg)
    for episode in range(3):
        env.reset(seed=episode)
        while env.t < 20:
            env.step({a: np.zeros(2, np.float32) for a in env.agents})
    env.close()
    names = sorted(p.name for p in (tmp_path / "fcd").glob("*.fcd.xml"))
    assert len(names) == 2 and names[0].endswith("ep00000.fcd.xml") \
        and names[1].endswith("ep00002.fcd.xml")


@pytest.mark.sumo
def test_city_rows_for_both_methods(city):
    rows = json.loads((city / "city.json").read_text())
    assert [r["method"] for r in rows] == ["coast", "sumo"]
    pol, sumo = rows
    for r in rows:
        assert tuple(r) == ROW_FIELDS and r["scenario"] == "cologne8" and r["seed"] == SEED
        # the same window: the scenario's begin + the warm-up, then 1 + STEPS steps of 0.1 s
        assert r["begin_s"] == pytest.approx(25200 + WARMUP)
        assert r["end_s"] == pytest.approx(25200 + WARMUP + (STEPS + 1) * 0.1)
        assert r["duration_s"] == pytest.approx((STEPS + 1) * 0.1, abs=1e-6)
        assert r["arrived"] > 0 and r["teleports"] == 0  # teleporting is off in both
        for f in ("travel_time_s", "waiting_time_s", "time_loss_s", "throughput_veh_h",
                  "mean_edge_speed_mps"):
            assert math.isfinite(r[f]) and r[f] >= 0, f
        assert 0 < r["mean_edge_speed_mps"] < 20 and r["travel_time_s"] > r["time_loss_s"]
        assert r["throughput_veh_h"] == pytest.approx(r["arrived"] * 3600 / r["duration_s"])
    assert sumo["collisions"] == 0 and sumo["agents"] == 0 and sumo["terminations"] == {}
    assert pol["agents"] > 6  # agents ended by an event were replaced by waiting vehicles
    assert pol["agent_steps"] >= pol["agents"]
    assert pol["peak_agents"] == 6 and sumo["peak_agents"] == 0  # the cap, reached
    ends = pol["terminations"]
    assert set(ends) == {"collision", "off_road", "red_light", "destination"}
    assert pol["removed"] == ends["collision"] + ends["off_road"] + ends["red_light"] > 0
    assert sum(ends.values()) <= pol["agents"]


@pytest.mark.sumo
def test_both_runs_cover_the_window_and_removed_agents_never_arrive(city):
    rows = {r["method"]: r for r in json.loads((city / "city.json").read_text())}
    base = city / "city" / "cologne8"
    assert (base / "warm.xml.gz").stat().st_size > 1000  # the state both runs load
    for m, r in rows.items():
        iv = ET.parse(base / m / "edgedata.xml").getroot().find("interval")
        assert float(iv.get("begin")) == pytest.approx(r["begin_s"])
        assert float(iv.get("end")) == pytest.approx(r["end_s"])
        trips = ET.parse(base / m / "tripinfo.xml").getroot().findall("tripinfo")
        assert all(r["begin_s"] <= float(t.get("arrival")) <= r["end_s"] + 1e-6 for t in trips)
    # the policy run: agents taken out by the env are in tripinfo as vaporized, not arrived
    trips = ET.parse(base / "coast" / "tripinfo.xml").getroot().findall("tripinfo")
    gone = [t.get("id") for t in trips if t.get("vaporized")]
    assert len(gone) >= rows["coast"]["removed"]
    again = summarise(base / "coast")
    assert again.arrived + rows["coast"]["terminations"]["destination"] \
        == rows["coast"]["arrived"]
    assert summarise(base / "coast", completed=gone).arrived == again.arrived + len(gone)
    # statistics of the SUMO runs give the collisions
    assert summarise(base / "sumo").collisions == 0


@pytest.mark.sumo
def test_report_city_table(city):
    rep = city / "report"
    html = (rep / "report.html").read_text()
    assert "City scenarios (SUMO outputs)" in html and '<table class="city">' in html
    table = html[html.index('<table class="city">'):]
    table = table[:table.index("</table>")]
    assert "<td>coast</td>" in table and "<td>sumo</td>" in table
    assert "travel time (s)" in table and "agent off road" in table
    assert "peak agents" in table and "acceleration JS" in table
    assert "Metrics against the baselines" not in html  # no recorded scenes here
    # per city: vehicles over time, travel times, speeds; and its drivers' kinematics against
    # the recorded humans; PNG inlined, SVG beside
    assert html.count('<img alt="vehicles over time, travel times and speeds of city') == 1
    assert html.count('<img alt="speed and acceleration of city cologne8') == 1
    assert "data:image/png;base64" in html
    assert sorted(p.suffix for p in (rep / "img").iterdir()) == [".png", ".png", ".svg", ".svg"]
    from magail_sumo.evaluation.city import completed_ids
    from magail_sumo.evaluation.traffic.sumo_outputs import run_distributions

    for method in ("coast", "sumo"):
        d = run_distributions(city / "city" / CFG.stem / method,
                              completed_ids(city / "city" / CFG.stem / method))
        assert d["running"].size > 0 and d["edge_speed_mps"][0].size > 0
    csv = (rep / "city.csv").read_text().splitlines()
    assert len(csv) == 3 and csv[0].startswith("scenario,method,begin_s,end_s,arrived")
    man = json.loads((city / "manifest.json").read_text())
    assert man["scenes"] == [] and man["city"]["file"] == "city.json"
    assert man["city"]["methods"] == ["coast", "sumo"] and man["city"]["steps"] == STEPS


@pytest.mark.sumo
def test_scenes_added_later_keep_the_city_results(city, tmp_path, capsys):
    out = tmp_path / "both"
    shutil.copytree(city, out)
    assert main(["evaluate", "--policy", "constvel", "--baselines", "logreplay", "--scenes",
                 str(WOMD_DIR / "850c48d8bbfa008f.tfrecord"), "--rollouts", "1", "--out",
                 str(out)]) == 0
    man = json.loads((out / "manifest.json").read_text())
    assert man["methods"] == ["constvel", "logreplay"] and man["city"]["methods"][0] == "coast"
    assert main(["report", str(out), "--workers", "1"]) == 0
    html = (out / "report" / "report.html").read_text()
    assert "Metrics against the baselines" in html and '<table class="city">' in html
    # a bad city.json is one error line naming the file and field; the scenes still report
    rows = json.loads((out / "city.json").read_text())
    rows[1]["travel_time_s"] = "fast"
    (out / "city.json").write_text(json.dumps(rows))
    capsys.readouterr()
    assert main(["report", str(out), "--workers", "1"]) == 1
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "city.json: row 1: travel_time_s must be a number" in err[0]
    assert "Metrics against the baselines" in (out / "report" / "report.html").read_text()


def test_manifest_of_another_run_setting_keeps_the_city_entry(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps(
        {"scenes": [], "methods": [], "seed": 0, "city": {"file": "city.json"}}))
    storage.write_manifest(tmp_path, {"scenes": [], "methods": ["constvel"], "rollouts": 2,
                                 "seed": 1})
    man = json.loads((tmp_path / "manifest.json").read_text())
    assert man["city"] == {"file": "city.json"} and man["methods"] == ["constvel"]


@pytest.mark.parametrize("args, message", [
    ([], "nothing to evaluate: give --scenes FILE..., --city SUMOCFG... or both"),
    (["--city", "missing.sumocfg"], "missing.sumocfg: not found (--city takes a SUMO "
                                    "scenario's configuration"),
    (["--city", "bad.sumocfg"], "bad.sumocfg: not valid XML"),
    (["--city", "nonet.sumocfg"], "nonet.sumocfg: names no net-file"),
    (["--city", str(CFG.with_suffix(".net.xml"))], "cologne8.net.xml: is not a SUMO "
                                                    "configuration"),
    (["--city", str(CFG), "--policy", "constvel"], "--policy constvel: a city needs a "
                                                    "driving policy"),
])
def test_bad_city_input_is_one_line(tmp_path, monkeypatch, capsys, args, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bad.sumocfg").write_text("<configuration><input>")
    (tmp_path / "nonet.sumocfg").write_text("<configuration><input/></configuration>")
    policy = [] if "--policy" in args else ["--policy", "random"]
    rc = main(["evaluate", *policy, *args, "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1, err
    assert err[0].startswith("error: magail-sumo evaluate: ") and message in err[0]
    assert not (tmp_path / "out").exists()  # refused before anything ran


def test_city_outputs_refuse_a_link_out_of_the_folder(tmp_path):
    """``OUT/city`` linked elsewhere: refused in one line before any SUMO run, nothing written
    there."""
    from magail_sumo.evaluation.city import CitySettings, evaluate_city
    from magail_sumo.outputs import OutputError, claim_output_dir

    out, outside = tmp_path / "out", tmp_path / "outside"
    outside.mkdir()
    claim_output_dir(out, "evaluate", ["manifest.json", "city", "city.json"])
    (out / "city").symlink_to(outside, target_is_directory=True)
    with pytest.raises(OutputError, match="would be written outside"):
        evaluate_city("random", [CFG], out, CitySettings(steps=5, warmup_s=0))
    assert list(outside.iterdir()) == []


def test_a_city_json_that_is_a_device_is_one_line(tmp_path):
    from magail_sumo.evaluation.city import read_rows
    from magail_sumo.evaluation.protocol import EvaluationError

    (tmp_path / "city.json").symlink_to("/dev/zero")
    with pytest.raises(EvaluationError, match=r"city.json: is a character device"):
        read_rows(tmp_path)


def test_city_json_written_before_peak_agents_still_reads(tmp_path):
    """Rows of an older city.json lack ``peak_agents``: read as NaN, the rest kept."""
    from magail_sumo.evaluation.city import read_rows

    row = {f: 0 for f in ROW_FIELDS if f != "peak_agents"}
    row.update(scenario="cologne8", method="sumo", terminations={})
    (tmp_path / "city.json").write_text(json.dumps([row]))
    (got,), _ = read_rows(tmp_path)
    assert math.isnan(got["peak_agents"]) and got["arrived"] == 0


@pytest.mark.sumo
def test_speed_and_acceleration_against_recorded_humans(city, humans):
    """Both rows compare their drivers' speed and 1-s acceleration distributions with the
    recorded humans'; kinematics.json holds the counts: the agents' samples are their
    agent-steps, SUMO's drivers' the passenger cars of SUMO's run each second (its FCD, read
    and removed), the humans' the expert's."""
    from magail_sumo.evaluation.city_kinematics import human_counts, js

    rows = {r["method"]: r for r in json.loads((city / "city.json").read_text())}
    kin = json.loads((city / "city" / "cologne8" / "kinematics.json").read_text())
    assert set(kin["methods"]) == {"coast", "sumo"}
    assert kin["humans"]["speed"] == human_counts(humans)["speed"]
    assert sum(kin["humans"]["speed"]) == kin["humans"]["transitions"] > 1000
    agents = kin["methods"]["coast"]
    # the agents after each step: those that acted, less those that left, plus the joiners
    assert abs(sum(agents["speed"]) - rows["coast"]["agent_steps"]) <= rows["coast"]["agents"]
    assert 0 < sum(agents["accel"]) < sum(agents["speed"])  # 1 s of history needed
    sumo = kin["methods"]["sumo"]
    assert sum(sumo["speed"]) > 10 * STEPS / 10 and 0 < sum(sumo["accel"]) < sum(sumo["speed"])
    assert not (city / "city" / "cologne8" / "sumo" / "fcd_1s.xml").exists()
    for method, r in rows.items():
        want = js(kin["methods"][method], kin["humans"])
        assert r["speed_js_humans"] == pytest.approx(want["speed"])
        assert r["accel_js_humans"] == pytest.approx(want["accel"])
        assert 0.0 < r["speed_js_humans"] < 1.0 and 0.0 < r["accel_js_humans"] < 1.0
    # coasting agents keep their speed: far narrower accelerations than SUMO's drivers
    assert rows["coast"]["accel_js_humans"] != rows["sumo"]["accel_js_humans"]


def test_kinematics_group_accelerations_over_one_second():
    """A vehicle gaining 1.25 m/s per second, sampled every 0.1 s: every acceleration sample
    is 1.25 m/s² once a second of its history is known; a vehicle seen only now has none."""
    from magail_sumo.evaluation.city_kinematics import Group
    from magail_sumo.evaluation.traffic.distributions import BINS

    g = Group(0.1)
    for k in range(30):
        g.add(["a"] + (["b"] if k == 29 else []), np.array([5.0 + 0.125 * k] + [3.0] * (k == 29)))
    lo, hi, n = BINS["linear_acceleration"]
    assert sum(g.counts["speed"]) == 31 and sum(g.counts["accel"]) == 20
    assert g.counts["accel"][int((1.25 - lo) / (hi - lo) * n)] == 20


def test_unusable_city_humans_is_one_line_before_anything_runs(tmp_path, capsys):
    """``--city-humans`` naming no expert data: one line naming the option and the folder,
    and no output folder made."""
    out = tmp_path / "out"
    (tmp_path / "empty").mkdir()
    for bad, why in ((tmp_path / "missing", "expert directory not found"),
                     (tmp_path / "empty", "not an expert directory")):
        assert main(["evaluate", "--policy", "random", "--city", str(CFG), "--city-humans",
                     str(bad), "--out", str(out)]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert err[-1].startswith("error: magail-sumo evaluate: --city-humans: ")
        assert str(bad) in err[-1] and why in err[-1]
        assert not out.exists()
