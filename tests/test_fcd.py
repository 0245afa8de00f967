"""SUMO FCD export of runs and their sumo-gui replay (magail_sumo.sim.fcd)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from magail_sumo.sim.fcd import KIND_COLORS, FcdRecorder, nav_angle, replay_paths

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "data" / "womd" / "637f20cafde22ff8.tfrecord"
BUNDLE = ROOT / "networks" / "637f20cafde22ff8"
NET = BUNDLE / "637f20cafde22ff8.net.xml"
TLL = BUNDLE / "637f20cafde22ff8.tll.xml"


def _cli(*args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "magail_sumo.cli.main", *args], cwd=ROOT,
                          capture_output=True, text=True, env=env, timeout=600)


def _read_fcd(path: Path) -> dict[tuple[float, str], dict[str, str]]:
    out = {}
    for ts in ET.parse(path).getroot():
        t = round(float(ts.get("time")), 2)
        for v in ts:
            out[(t, v.get("id"))] = dict(v.attrib)
    return out


def _sumo_back(cfg: Path, tmp: Path) -> dict:
    """Run the replay config in plain SUMO; its own FCD output."""
    from converters.sumo.tools import binary

    back = tmp / "back.fcd.xml"
    subprocess.run([binary("sumo"), "-c", str(cfg), "--fcd-output", str(back)], check=True,
                   capture_output=True, timeout=300)
    return _read_fcd(back)


def _inner_errors(fcd: dict, back: dict) -> np.ndarray:
    """Position errors (m) of the records other than each object's first and last (insertion
    and exit steps); inf where SUMO has no such vehicle at that time."""
    times: dict[str, list[float]] = {}
    for t, i in fcd:
        times.setdefault(i, []).append(t)
    err = []
    for (t, i), rec in fcd.items():
        if t in (min(times[i]), max(times[i])):
            continue
        b = back.get((t, i))
        err.append(np.inf if b is None else np.hypot(float(rec["x"]) - float(b["x"]),
                                                    float(rec["y"]) - float(b["y"])))
    return np.array(err)


def test_nav_angle_is_clockwise_from_north():
    yaw = np.array([0.0, np.pi / 2, np.pi, -np.pi / 2])
    np.testing.assert_allclose(nav_angle(yaw), [90.0, 0.0, 270.0, 180.0], atol=1e-9)


def test_recorder_writes_sumo_fcd(tmp_path):
    rec = FcdRecorder(0.1)
    rec.add(0.0, ["a", "b"], np.array([0.0, 10.0]), np.array([0.0, 5.0]),
            np.array([0.0, np.pi / 2]), [4.0, 2.0], [2.0, 1.0], ["agent", "log"],
            ["passenger", "pedestrian"])
    rec.add(0.1, ["a"], np.array([1.0]), np.array([0.0]), np.array([0.0]), [4.0], [2.0])
    assert len(rec) == 3 and rec.end_time() == pytest.approx(0.1)
    fcd, types, cfg = replay_paths(tmp_path / "run")
    assert (fcd.name, types.name, cfg.name) == ("run.fcd.xml", "run.types.add.xml", "run.sumocfg")
    assert rec.write_fcd(fcd) == 3
    got = _read_fcd(fcd)
    a0, b0, a1 = got[(0.0, "a")], got[(0.0, "b")], got[(0.1, "a")]
    assert float(a0["x"]) == pytest.approx(2.0)  # front bumper: centre + length / 2
    assert float(b0["y"]) == pytest.approx(6.0) and float(b0["angle"]) == pytest.approx(0.0)
    assert float(a0["angle"]) == pytest.approx(90.0)
    assert float(a0["speed"]) == pytest.approx(10.0) == pytest.approx(float(a1["speed"]))
    assert a0["type"] != b0["type"] and "lane" not in a0
    rec.write_types(types)
    vt = {v.get("id"): v.attrib for v in ET.parse(types).getroot()}
    assert vt[a0["type"]]["color"] == KIND_COLORS["agent"]
    assert vt[b0["type"]]["guiShape"] == "pedestrian"
    assert float(vt[b0["type"]]["length"]) == pytest.approx(2.0)


@pytest.fixture(scope="module")
def replay_run(tmp_path_factory):
    """``magail-sumo replay --fcd`` of the bundled scene (log replay)."""
    out = tmp_path_factory.mktemp("fcd_replay")
    proc = _cli("replay", str(SCENE), "--out", str(out / "v.gif"), "--size", "64",
                "--fcd", str(out / "run.fcd.xml"))
    assert proc.returncode == 0, proc.stderr
    assert "sumo-gui -c" in proc.stderr
    return out


@pytest.mark.sumo
def test_replay_cli_fcd_reproduces_the_run_in_sumo(replay_run, tmp_path):
    cfg = replay_run / "run.sumocfg"
    root = ET.parse(cfg).getroot()
    net = root.find("./input/net-file").get("value")
    assert (cfg.parent / net).resolve() == NET.resolve()  # the shipped bundle's network
    fcd = _read_fcd(replay_run / "run.fcd.xml")
    assert len({i for _, i in fcd}) > 50 and all(r.get("lane") for r in fcd.values())
    back = _sumo_back(cfg, tmp_path)
    err = _inner_errors(fcd, back)
    assert err.size > 3000
    assert np.mean(err < 0.05) > 0.95, np.percentile(err, [50, 90, 99])


@pytest.mark.sumo
def test_env_fcd_every_records_chosen_episodes(tmp_path):
    from magail_sumo.env import EnvConfig, SumoDrivingEnv
    from magail_sumo.env.log_actions import expert_actions

    cfg = EnvConfig(max_steps=4, fcd_dir=str(tmp_path / "fcd"), fcd_every=2,
                    terminate_on=())
    env = SumoDrivingEnv(str(SCENE), BUNDLE, cfg)
    for ep in range(3):
        env.reset(seed=ep)
        while env.agents:
            env.step(expert_actions(env))
    env.close()
    files = sorted(p.name for p in (tmp_path / "fcd").iterdir())
    cfgs = [f for f in files if f.endswith(".sumocfg")]
    assert len(cfgs) == 2 and cfgs[0].endswith("ep00000.sumocfg") \
        and cfgs[1].endswith("ep00002.sumocfg"), files
    fcd = _read_fcd(tmp_path / "fcd" / cfgs[0].replace(".sumocfg", ".fcd.xml"))
    assert {t for t, _ in fcd} >= {0.0, 0.4}
    with pytest.raises(Exception, match="fcd_every"):
        EnvConfig(fcd_every=-1)


@pytest.mark.sumo
def test_evaluate_fcd_rollouts(tmp_path):
    proc = _cli("evaluate", "--policy", "constvel", "--baselines", "none", "--rollouts", "2",
                "--fcd-rollouts", "1", "--scenes", str(SCENE), "--networks",
                str(ROOT / "networks"), "--out", str(tmp_path / "ev"))
    assert proc.returncode == 0, proc.stderr
    folder = tmp_path / "ev" / "fcd" / "constvel" / "637f20cafde22ff8"
    assert sorted(p.name for p in folder.iterdir()) == [
        "rollout000.fcd.xml", "rollout000.sumocfg", "rollout000.types.add.xml"]
    fcd = _read_fcd(folder / "rollout000.fcd.xml")
    assert max(t for t, _ in fcd) == pytest.approx(9.0 + 0.1)  # 91 steps, then the exit step
    err = _inner_errors(fcd, _sumo_back(folder / "rollout000.sumocfg", tmp_path))
    assert np.mean(err < 0.05) > 0.9


# ----------------------------------------------------------------------------- sumo-gui
def _xvfb():
    """A started Xvfb server and its DISPLAY, or a skip reason."""
    exe = shutil.which("Xvfb")
    if exe is None:
        return None, "Xvfb not installed (apt-get install xvfb; .ci/run installs it)"
    r, w = os.pipe()
    proc = subprocess.Popen([exe, "-displayfd", str(w), "-screen", "0", "1024x768x24",
                             "-nolisten", "tcp"], pass_fds=(w,), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    os.close(w)
    with os.fdopen(r) as fh:
        num = fh.readline().strip()
    if not num:
        proc.kill()
        return None, "Xvfb did not start"
    return proc, f":{num}"


def _snapshot(cfg: Path, png: Path, time_s: float, display: str, extra: list[str]) -> None:
    from converters.sumo.tools import binary

    settings = png.with_suffix(".view.xml")
    settings.write_text(f'<viewsettings>\n  <delay value="0"/>\n'
                        f'  <snapshot file="{png.name}" time="{time_s}"/>\n</viewsettings>\n')
    env = dict(os.environ, DISPLAY=display)
    proc = subprocess.run([binary("sumo-gui"), "-c", str(cfg), "--gui-settings-file",
                           str(settings), "--start", "--quit-on-end", "--window-size", "800,600",
                           *extra], cwd=png.parent, env=env, capture_output=True, text=True,
                          timeout=300)
    # sumo-gui 1.28 sometimes crashes while quitting under Xvfb, after the snapshot is written
    assert png.is_file() and png.stat().st_size > 0, \
        f"sumo-gui wrote no snapshot (exit {proc.returncode}): {proc.stderr[-500:]}"


@pytest.mark.sumo
def test_sumo_gui_shows_the_replay(replay_run, tmp_path):
    from PIL import Image

    try:
        from converters.sumo.tools import binary
        binary("sumo-gui")
    except Exception as exc:  # noqa: BLE001
        pytest.skip(f"sumo-gui not available: {exc}")
    xvfb, display = _xvfb()
    if xvfb is None:
        pytest.skip(display)
    try:
        shot = tmp_path / "replay.png"
        _snapshot(replay_run / "run.sumocfg", shot, 3.0, display, [])
        # the same view without the recorded vehicles
        empty = tmp_path / "empty.png"
        cfg = tmp_path / "empty.sumocfg"
        cfg.write_text(f'<configuration><input><net-file value="{NET}"/></input>'
                       '<time><end value="3.1"/></time></configuration>')
        _snapshot(cfg, empty, 3.0, display, [])
    finally:
        xvfb.kill()
        xvfb.wait()
    img = np.asarray(Image.open(shot).convert("RGB")).astype(np.int32)
    base = np.asarray(Image.open(empty).convert("RGB")).astype(np.int32)
    assert img.shape[0] > 100 and img.shape[1] > 100
    assert img.std() > 10  # not blank
    agent = np.array([int(c) for c in KIND_COLORS["agent"].split(",")])
    near = lambda im: (np.abs(im - agent).max(axis=2) < 40).sum()  # noqa: E731
    assert near(img) > 100, "no policy-coloured vehicles drawn"
    assert near(base) < near(img) / 10


@pytest.mark.sumo
def test_training_workers_record_episodes(tmp_path):
    """``env.fcd_dir`` / ``env.fcd_every`` of a training config: every scene worker of the
    vectorised env writes its chosen episodes."""
    from magail_sumo.env import EnvConfig
    from magail_sumo.env.vec_env import MultiSceneVecEnv
    from magail_sumo.env.scene_specs import scene_specs

    specs = scene_specs([SCENE], ROOT / "networks", convert_missing=False)
    cfg = EnvConfig(controlled=4, max_steps=5, fcd_dir=str(tmp_path / "fcd"), fcd_every=3)
    venv = MultiSceneVecEnv(specs, cfg, seed=0)
    try:
        venv.reset()
        while venv.episodes < 1:
            venv.step(np.zeros((venv.num_envs, 2), np.float32))
    finally:
        venv.close()
    cfgs = sorted(p.name for p in (tmp_path / "fcd").glob("*.sumocfg"))
    assert [c.rsplit("-", 1)[1] for c in cfgs] == ["ep00000.sumocfg"], cfgs
    fcd = _read_fcd(tmp_path / "fcd" / cfgs[0].replace(".sumocfg", ".fcd.xml"))
    times = {t for t, _ in fcd}
    assert 0.0 in times and len(times) >= 2  # the episode ends when its agents do


@pytest.mark.sumo
def test_replay_cli_fcd_with_a_bundle_converted_on_the_fly(tmp_path):
    """A scene without a shipped bundle: the network is copied beside the FCD."""
    scene = ROOT / "data" / "womd" / "850c48d8bbfa008f.tfrecord"
    proc = _cli("replay", str(scene), "--out", str(tmp_path / "v.gif"), "--size", "64",
                "--fcd", str(tmp_path / "x"))
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "v.gif", "x.fcd.xml", "x.net.xml", "x.sumocfg", "x.types.add.xml"]
    assert ET.parse(tmp_path / "x.sumocfg").getroot().find("./input/net-file").get("value") \
        == "x.net.xml"
    fcd = _read_fcd(tmp_path / "x.fcd.xml")
    (tmp_path / "back").mkdir()
    err = _inner_errors(fcd, _sumo_back(tmp_path / "x.sumocfg", tmp_path / "back"))
    assert err.size > 300 and np.mean(err < 0.05) > 0.95


@pytest.mark.sumo
def test_city_env_run_replays_in_sumo(tmp_path):
    from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv

    cfg = ROOT / "data" / "sumo" / "ingolstadt21" / "ingolstadt21.sumocfg"
    env = SumoCityEnv(cfg, CityEnvConfig(warmup_s=120, max_steps=20, control_fraction=0.5))
    env.record_fcd()
    env.reset(seed=0)
    while env.agents:
        env.step({a: np.array([0.2, 0.0], np.float32) for a in env.agents})
    files = env.write_fcd(tmp_path / "city.fcd.xml")
    env.close()
    fcd = _read_fcd(files.fcd)
    assert files.records == len(fcd) and len({i for _, i in fcd}) >= 10
    (tmp_path / "back").mkdir()
    err = _inner_errors(fcd, _sumo_back(files.sumocfg, tmp_path / "back"))
    assert err.size and np.mean(err < 0.05) > 0.9
