"""SumoSession on a real converted scene: stepping, bulk state, moveToXY, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import WOMD_DIR
from converters import load_scene
from magail_sumo.sim.frames import centre_to_front, front_to_centre, sumo_angle_to_yaw, yaw_to_sumo_angle
from magail_sumo.sim.session import SessionConfig, SimulationError, SumoSession


@pytest.fixture(scope="module")
def bundle(bundled_networks):
    scene = load_scene(WOMD_DIR / "850c48d8bbfa008f.tfrecord")
    folder = bundled_networks.bundle(scene.scenario_id)
    return scene, folder / f"{scene.scenario_id}.sumocfg"


def test_frame_conventions():
    yaw = np.array([0.0, np.pi / 2, -np.pi / 2, np.pi - 1e-9])
    assert yaw_to_sumo_angle(yaw)[:3].tolist() == [90.0, 0.0, 180.0]
    np.testing.assert_allclose(sumo_angle_to_yaw(yaw_to_sumo_angle(yaw))[:3], yaw[:3])
    fx, fy = centre_to_front(np.zeros(1), np.zeros(1), np.array([np.pi / 2]), np.array([4.0]))
    assert fx[0] == pytest.approx(0.0) and fy[0] == pytest.approx(2.0)
    cx, cy = front_to_centre(fx, fy, np.array([np.pi / 2]), np.array([4.0]))
    assert cx[0] == pytest.approx(0.0, abs=1e-12) and cy[0] == pytest.approx(0.0)


@pytest.mark.sumo
def test_step_state_and_move_to_logged_pose(bundle):
    scene, cfg = bundle
    tr = scene.tracks
    with SumoSession(cfg) as sim:
        departed = []
        for _ in range(5):
            departed += sim.step()[0]
        assert sim.time == pytest.approx(0.5)
        veh = sim.vehicles()
        assert len(veh) == len(departed) > 0
        # place every vehicle at its recorded pose of the next step: SUMO reports it exactly
        t = 6
        rows = [int(np.flatnonzero(tr.id == int(v))[0]) for v in veh.ids]
        ok = [k for k, r in enumerate(rows) if tr.valid[r, t]]
        ids = [veh.ids[k] for k in ok]
        r = np.array([rows[k] for k in ok])
        sim.move(ids, tr.x[r, t], tr.y[r, t], tr.heading[r, t].astype(float), veh.length[ok])
        sim.step()
        after = sim.vehicles()
        idx = [after.ids.index(v) for v in ids]
        np.testing.assert_allclose(after.x[idx], tr.x[r, t], atol=1e-6)
        np.testing.assert_allclose(after.y[idx], tr.y[r, t], atol=1e-6)


@pytest.mark.sumo
def test_one_simulation_per_process(bundle):
    _, cfg = bundle
    with SumoSession(cfg):
        with pytest.raises(SimulationError, match="already running"):
            SumoSession(cfg).start()


@pytest.mark.sumo
def test_bad_inputs(tmp_path, bundle):
    _, cfg = bundle
    with pytest.raises(SimulationError, match="missing.sumocfg: SUMO config file not found"):
        SumoSession(tmp_path / "missing.sumocfg").start()
    broken = tmp_path / "broken.sumocfg"
    broken.write_text("<configuration><input><net-file value='nope.net.xml'/></input>")
    with pytest.raises(SimulationError, match="broken.sumocfg: not valid XML"):
        SumoSession(broken).start()
    bad_routes = tmp_path / "bad.rou.xml"
    bad_routes.write_text('<routes><vehicle id="v" depart="0"><route edges="no_such_edge"/>'
                          "</vehicle></routes>")
    net = next(cfg.parent.glob("*.net.xml"))
    with pytest.raises(SimulationError, match="no_such_edge"):
        with SumoSession(net=net, routes=[bad_routes],
                         config=SessionConfig(extra_args=("--end", "5"))) as sim:
            for _ in range(3):
                sim.step()
    # after failures a new session still starts
    with SumoSession(cfg) as sim:
        sim.step()


@pytest.mark.sumo
def test_move_far_off_the_road_is_exact(bundle):
    """No lane within the fast 5 m match threshold: the vehicle is still placed exactly."""
    import libsumo

    from magail_sumo.sensors.raycast import polyline_segments

    scene, cfg = bundle
    with SumoSession(cfg) as sim:
        for _ in range(5):
            sim.step()
        veh = sim.vehicles()
        vid = next(v for v in veh.ids if not libsumo.vehicle.getStops(v))
        k = veh.ids.index(vid)
        s, e = polyline_segments([np.asarray(libsumo.lane.getShape(lane))
                                  for lane in libsumo.lane.getIDList()])

        def lane_distance(p):
            w, d = p - s, e - s
            t = np.clip((w * d).sum(1) / np.maximum((d * d).sum(1), 1e-9), 0, 1)
            return float(np.hypot(*(w - t[:, None] * d).T).min())

        side = np.array([-np.sin(veh.yaw[k]), np.cos(veh.yaw[k])])
        target = next(p for off in (8.0, 12.0, 20.0, 30.0, 45.0, -8.0, -12.0, -20.0, -30.0)
                      for p in [np.array([veh.x[k], veh.y[k]]) + off * side]
                      if 6.0 < lane_distance(p) < 90.0)
        assert lane_distance(target) > 5.0  # out of reach of the fast match
        sim.move([vid], target[:1], target[1:], veh.yaw[k:k + 1], veh.length[k:k + 1])
        sim.step()
        after = sim.vehicles()
        j = after.ids.index(vid)
        assert after.x[j] == pytest.approx(target[0], abs=1e-6)
        assert after.y[j] == pytest.approx(target[1], abs=1e-6)
