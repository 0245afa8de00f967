"""Route-relative control (``action_layout: accel_offset``): reference paths, the pure-pursuit
steering along them, the SUMO route's lanes as a city agent's path, and the layout in both envs
(a real city and a real recorded scene)."""

from __future__ import annotations

import collections

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR
from magail_sumo.sim import dynamics, tracking
from magail_sumo.sim.paths import Paths, resample

CITY = ROOT / "data" / "sumo" / "ingolstadt21" / "ingolstadt21.sumocfg"
SID = "637f20cafde22ff8"


def _arc_path(radius: float = 15.0) -> np.ndarray:
    """20 m straight along +x, a left quarter circle of ``radius``, 20 m straight along +y."""
    a = np.linspace(-np.pi / 2, 0.0, 40)
    arc = np.stack([20.0 + radius * np.cos(a), radius + radius * np.sin(a)], axis=1)
    return np.concatenate([[[0.0, 0.0]], arc, [[20.0 + radius, radius + 20.0]]])


def test_resample_is_equally_spaced_and_keeps_the_ends():
    p, s = resample(np.array([[0.0, 0.0], [0.0, 0.0], [2.5, 0.0], [2.5, 2.5]]), 1.0)
    assert p[0].tolist() == [0.0, 0.0] and p[-1].tolist() == [2.5, 2.5]
    assert s[-1] == pytest.approx(5.0) and np.allclose(np.diff(s), 5.0 / 5)
    assert p[2] == pytest.approx([2.0, 0.0])  # 2 m along the polyline
    assert resample(np.array([[3.0, 4.0], [3.0, 4.0]]))[0].shape == (1, 2)
    with pytest.raises(ValueError):
        resample(np.full((2, 2), np.nan))


def test_paths_project_at_ahead_and_turn():
    paths = Paths.empty(paths=1, points=4)  # grows as paths are added
    straight = paths.add(np.array([[0.0, 0.0], [100.0, 0.0]]))
    bend = paths.add(_arc_path())
    point = paths.add(np.array([[5.0, 5.0]]))
    assert len(paths) == 3 and paths.length(np.array([straight]))[0] == pytest.approx(100.0)
    rows = np.array([straight, straight])
    at, s = paths.project(rows, np.array([10.3, 50.0]), np.array([2.0, -1.0]))
    assert s == pytest.approx([10.3, 50.0])
    # windowed: a hint near the point finds the same progress
    at2, s2 = paths.project(rows, np.array([10.3, 50.0]), np.array([2.0, -1.0]), at)
    assert (at2 == at).all() and s2 == pytest.approx(s)
    x, y, h = paths.at(np.array([straight, bend, point]), np.array([250.0, 0.0, 3.0]))
    assert [x[0], y[0], h[0]] == pytest.approx([100.0, 0.0, 0.0])  # clamped to the end
    assert [x[1], y[1]] == pytest.approx([0.0, 0.0]) and h[1] == pytest.approx(0.0, abs=1e-6)
    assert [x[2], y[2], h[2]] == [5.0, 5.0, 0.0]
    # the bend turns left by 90 degrees between its start and its end
    assert paths.turn(np.array([bend]), np.array([0.0]), 200.0)[0] == \
        pytest.approx(np.pi / 2, abs=0.05)
    # 10 m ahead of an agent at x=5 on the straight, 1 m left of it, heading +x: (10, -1)
    got = paths.ahead(np.array([straight]), np.array([5.0]), np.array([5.0]), np.array([1.0]),
                      np.array([0.0]), (10.0,))
    assert got[0] == pytest.approx([10.0, -1.0], abs=1e-5)


def test_paths_carry_the_roads_speed_limits_and_the_lowest_ahead():
    """A path added with per-point speed limits keeps, at each resampled point, the limit of
    the segment it lies on; the query gives the limit at the progress point and the lowest
    one within reach with its distance (0 / unknown: the limit here)."""
    # 0-10 m at 13.9 m/s, a repeated point, 10-20 m at 8.3, 20-30 m unknown
    pts = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
    paths = Paths.of([pts, pts], limits=[np.array([13.9, 99.0, 8.3, 0.0, 0.0]), None])
    lim = paths.limit[paths.start[0]:paths.start[0] + paths.count[0]]
    assert lim[:10].tolist() == [13.9] * 10 and lim[10:20].tolist() == [8.3] * 10
    assert (lim[20:] == 0).all() and (paths.limit[paths.start[1]:paths.n_points] == 0).all()
    here, low, gap = paths.limits_ahead(np.array([0, 0, 0, 1]), np.array([2, 12, 25, 2]), 50.0)
    assert here.tolist() == [13.9, 8.3, 0.0, 0.0]
    assert low.tolist() == [8.3, 8.3, 0.0, 0.0] and gap.tolist() == [8.0, 0.0, 0.0, 0.0]
    # out of reach: the limit here
    _, low, gap = paths.limits_ahead(np.array([0]), np.array([2]), 5.0)
    assert (low[0], gap[0]) == (13.9, 0.0)


def test_pursuit_converges_to_the_path_and_to_the_offset():
    """A car starting 1 m right of a path converges onto it, through a 15-m-radius left turn,
    and holds a commanded 1-m offset to its left."""
    paths = Paths.of([_arc_path()])
    lim = dynamics.BicycleLimits()
    for offset, want in ((0.0, 0.0), (1.0, 1.0)):
        st = dynamics.VehicleState(np.array([0.0]), np.array([-1.0]), np.array([0.0]),
                                   np.array([8.0]))
        hint, errs = np.zeros(1, np.int64), []
        for _ in range(70):
            steer, hint = tracking.follow(paths, np.array([0]), hint, st, np.array([2.9]),
                                          np.array([offset]), lim)
            st = dynamics.step(st, np.zeros(1), steer, np.array([2.9]), 0.1, lim)
            _, s = paths.project(np.array([0]), st.x, st.y, hint)
            px, py, h = paths.at(np.array([0]), s)
            errs.append(float(-np.sin(h[0]) * (st.x[0] - px[0]) + np.cos(h[0]) * (st.y[0] - py[0])))
        errs = np.array(errs)
        assert abs(errs[-1] - want) < 0.1  # on the final straight, at the offset
        assert np.abs(errs[30:] - want).max() < 0.6  # through the bend
    assert st.y[0] > 25.0  # it drove around the bend


def test_accel_offset_layout_units_and_expert_relayout():
    lim = dynamics.BicycleLimits(max_offset=2.0)
    accel, off = dynamics.denormalise(np.array([[0.5, -0.5]]), lim, "accel_offset")
    assert accel[0] == pytest.approx(3.0) and off[0] == pytest.approx(-1.0)
    assert dynamics.normalise(accel, off, lim, "accel_offset").tolist() == [[0.5, -0.5]]
    rec = np.array([[0.2, -0.7], [-0.1, 0.3]], np.float32)
    assert dynamics.relayout(rec, "accel_offset").tolist() == \
        [[pytest.approx(0.2), 0.0], [pytest.approx(-0.1), 0.0]]
    assert dynamics.relayout(rec, "steer_throttle").tolist() == rec[:, ::-1].tolist()
    assert tracking.no_reverse(np.array([-10.0, -1.0]), np.array([0.5, 20.0]), 0.1).tolist() \
        == [-5.0, -1.0]


def _city_run(layout: str, steps: int = 300):
    from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv
    from magail_sumo.sensors.config import ObservationConfig
    from magail_sumo.sensors.observation import observation_names

    ob = ObservationConfig(route_points=(10.0, 30.0), command=True)
    env = SumoCityEnv(CITY, CityEnvConfig(max_agents=60, warmup_s=300, max_steps=steps,
                                          action_layout=layout, observation=ob))
    names = observation_names(ob)
    cols = [names.index(c) for c in ("route_x_10", "route_y_10")]
    reasons, near = collections.Counter(), []
    try:
        obs, _ = env.reset(seed=0)
        for _ in range(steps):
            f = env.fleet
            k = f.live()
            # a plain speed keeper (10 m/s), no steering / no offset
            a = np.clip(0.5 * (10.0 - f.speed[k]) / 6.0, -1.0, 1.0)
            acts = {f.names[j]: np.array([a[i], 0.0], np.float32) for i, j in enumerate(k)}
            obs, _, term, trunc, info = env.step(acts)
            near += [np.hypot(*o[cols]) for o in obs.values()]
            for name in term:
                if term[name] or trunc[name]:
                    reasons[info[name]["reason"]] += 1
        return reasons, np.array(near), env.cut_paths, len(env.paths)
    finally:
        env.close()


@pytest.mark.sumo
def test_city_agents_follow_their_routes_lanes():
    """On the real ingolstadt21 city, agents holding a speed with no lateral action stay on
    their routes' lanes through the junctions (no agent leaves the road); steering straight
    ahead instead (``accel_steer``) takes agents off the road. Every agent has a path, the
    route look-ahead reads it."""
    route, near, cut, n_paths = _city_run("accel_offset")
    assert route["off_road"] == 0, route
    assert route["destination"] + route["arrived"] > 0  # trips end at their routes' ends
    assert cut == 0 and n_paths > 60
    # 10 m along the route from the agent's progress point: about 10 m away (less on a bend,
    # a little more when the agent is beside its lane's centreline or at its path's start)
    assert near.size and np.percentile(near, 99) <= 10.6 and 9.0 < np.median(near) <= 10.01
    free, *_ = _city_run("accel_steer")
    assert free["off_road"] >= 10, free


@pytest.mark.sumo
def test_route_paths_cross_junctions_on_every_internal_lane():
    """A connection that crosses its junction on two internal lanes (a left turn waiting
    inside the junction: libsumo gives the first internal lane's link as the lane reached plus
    the next internal lane) is followed on both: on the real cologne8 network every
    connection's chain of internal lanes joins up, end to start, from the lane it leaves to the
    lane it reaches (before, the second internal lane was skipped and the path cut a chord
    across the junction, up to 20.8 m off its lanes)."""
    from magail_sumo.sim.lane_graph import LaneGraph
    from magail_sumo.sim.session import SessionConfig, SumoSession

    net = ROOT / "data" / "sumo" / "cologne8" / "cologne8.net.xml"
    with SumoSession(net=net, config=SessionConfig(subscribe=False)) as sess:
        api = sess.api
        g = LaneGraph(api)
        junction = ":cluster_1098574052_1098574061_247379905"
        assert g._via("-28675510#11_0", "-22917421#14") == (
            "-22917421#14_0", [f"{junction}_14_0", f"{junction}_22_0"])
        gaps, two = [], 0
        for lane in api.lane.getIDList():
            if lane.startswith(":"):
                continue
            for reached, via in g.links(lane):
                if not via:
                    continue
                chain = g.internal_chain(via)
                two += len(chain) > 1
                ends = [g.shape(lane)] + [g.shape(x) for x in chain] + [g.shape(reached)]
                gaps += [float(np.hypot(*(a[-1] - b[0]))) for a, b in zip(ends, ends[1:])]
    assert two >= 20  # cologne8 has many such connections
    assert max(gaps) < 0.5, max(gaps)


@pytest.mark.sumo
def test_recorded_scene_expert_follows_its_recorded_route():
    """In a real recorded scene, the expert's accelerations with offset 0 (its actions in the
    ``accel_offset`` layout) keep every agent within centimetres of its recorded track."""
    from converters import load_scene
    from magail_sumo.env import EnvConfig, SumoDrivingEnv
    from magail_sumo.env.log_actions import expert_actions

    scene = load_scene(WOMD_DIR / f"{SID}.tfrecord")
    tr = scene.tracks
    env = SumoDrivingEnv(scene, ROOT / "networks" / SID,
                         EnvConfig(controlled="all", start_step=10, terminate_on=(),
                                   action_layout="accel_offset"))
    errs = []
    try:
        env.reset(seed=0)
        assert env.paths is not None and len(env.paths) == len(env.fleet)
        while env.agents:
            acts = expert_actions(env)
            assert all(a[1] == 0.0 for a in acts.values())
            env.step(acts)
            f = env.fleet
            k = f.live()
            rows, t = env._ctrl[k], env.t
            v = tr.valid[rows, t]
            errs.append(np.hypot(f.x[k][v] - tr.x[rows[v], t], f.y[k][v] - tr.y[rows[v], t]))
    finally:
        env.close()
    e = np.concatenate(errs)
    assert e.size > 500 and np.median(e) < 0.05 and np.percentile(e, 95) < 0.3


@pytest.mark.sumo
def test_city_progress_reward_is_the_distance_along_the_route():
    """With ``progress_reward`` c, an agent's reward is c times the metres it moved along its
    route in the step: for agents following their routes, about c · speed · dt."""
    from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv

    env = SumoCityEnv(CITY, CityEnvConfig(max_agents=30, warmup_s=300, max_steps=60,
                                          action_layout="accel_offset", progress_reward=0.5))
    got, want = [], []
    try:
        env.reset(seed=0)
        for _ in range(60):
            f = env.fleet
            k = f.live()
            acts = {f.names[j]: np.array([0.1, 0.0], np.float32) for j in k}
            _, rew, term, trunc, _ = env.step(acts)
            for name in acts:
                if not (term[name] or trunc[name]):
                    got.append(rew[name])
                    want.append(0.5 * f.speed[f.index[name]] * env.dt)
    finally:
        env.close()
    got, want = np.array(got), np.array(want)
    assert got.size > 500 and got.min() > -1e-6
    assert np.median(np.abs(got - want)) < 0.01 and np.corrcoef(got, want)[0, 1] > 0.95
    with pytest.raises(ValueError, match="progress_reward"):
        CityEnvConfig(progress_reward=-1.0)


def _pursue(paths, st, lim, steps: int):
    """``st`` after ``steps`` 0.1-s steps of pure pursuit along path 0 at no acceleration."""
    hint = np.zeros(1, np.int64)
    for _ in range(steps):
        steer, hint = tracking.follow(paths, np.array([0]), hint, st, np.array([2.9]),
                                      np.zeros(1), lim)
        st = dynamics.step(st, np.zeros(1), steer, np.array([2.9]), 0.1, lim)
    return st


def test_pursuit_past_the_paths_end_drives_on():
    """A car overshooting the end of its path keeps its heading: the goal runs on along the
    path's last direction instead of pulling it back round."""
    paths = Paths.of([np.array([[0.0, 0.0], [10.0, 0.0]])])
    lim = dynamics.BicycleLimits()
    st = dynamics.VehicleState(np.array([9.0]), np.array([0.0]), np.array([0.0]),
                               np.array([10.0]))
    st = _pursue(paths, st, lim, 30)
    assert st.x[0] > 35.0 and abs(st.y[0]) < 0.05 and abs(st.yaw[0]) < 0.01
    # slow (the least look-ahead) and beside the line: far past the end the progress point
    # runs on too, so the goal stays ahead (a clamped one fell behind and turned the car round,
    # as recorded creepers with 5-m routes did in the womd14 test windows)
    st = dynamics.VehicleState(np.array([9.0]), np.array([0.3]), np.array([0.0]),
                               np.array([3.0]))
    st = _pursue(paths, st, lim, 80)
    assert st.x[0] > 30.0 and abs(st.y[0]) < 0.3 and abs(st.yaw[0]) < 0.05
    at, s = paths.project(np.array([0]), np.array([25.0]), np.array([0.5]))
    assert at[0] == len(paths.points(0)) - 1 and s[0] == pytest.approx(25.0)


def test_idm_acceleration_and_its_bend_and_light_rules():
    """IDM: free road accelerates below the desired speed; a close standing leader brakes;
    a bend ahead lowers the desired speed; a red light brakes to stop before its stop line,
    the harder the nearer the line; a light with its line out of range, or green, does not;
    a junction conflict is given way to only when the road user would arrive too soon."""
    from magail_sumo.agents.idm import IdmPolicy
    from magail_sumo.models.idm import IdmParams, bend_speed, idm_accel
    from magail_sumo.sensors.observation import observation_names

    p = IdmParams()
    a = idm_accel(np.array([5.0, 10.0, 10.0]), np.array([np.inf, np.inf, 8.0]),
                  np.array([0.0, 0.0, 10.0]), p)
    assert 0 < a[1] < a[0] <= p.a_max and a[2] < -3.0
    straight = np.array([[5.0, 0.0, 10.0, 0.0, 20.0, 0.0]])
    bend = np.array([[5.0, 0.5, 9.0, 3.0, 12.0, 14.0]])
    assert bend_speed(straight, 2.0)[0] > 100 and bend_speed(bend, 2.0)[0] < 6.0
    pol = IdmPolicy(speed_limits=True)  # unknown limits (0) change nothing
    names = observation_names(pol.observation)
    obs = np.zeros(len(names), np.float32)
    obs[names.index("speed")] = 10.0
    obs[names.index("leader_gap")] = pol.observation.leader_range  # none
    obs[names.index("path_leader_gap")] = pol.observation.leader_range  # none
    obs[names.index("light_gap")] = 50.0  # none
    obs[[names.index("give_way_gap"), names.index("give_way_time")]] = (50.0, 10.0)  # none
    obs[[names.index(f"route_x_{d:g}") for d in (5, 10, 20)]] = (5.0, 10.0, 20.0)
    free = pol.act({"a": obs})["a"]
    assert free[0] > 0 and free[1] == 0.0
    obs[names.index("light")] = 3.0
    assert pol.act({"a": obs})["a"][0] == free[0]  # red, but no stop line within range
    obs[names.index("light_gap")] = 40.0
    far = pol.act({"a": obs})["a"][0]
    obs[names.index("light_gap")] = 15.0
    near = pol.act({"a": obs})["a"][0]
    assert near < far < 0  # the nearer the line, the harder the braking
    accel = pol.rule.accel(obs[None])[0]
    assert accel == pytest.approx(-10.0 ** 2 / (2 * (15.0 - p.s0)))
    standing = obs.copy()
    standing[[names.index("speed"), names.index("light_gap")]] = (0.0, p.s0 + 0.5)
    assert pol.rule.accel(standing[None])[0] == -p.max_brake  # held at the line, no creeping
    obs[names.index("light")] = 1.0
    assert pol.act({"a": obs})["a"][0] == free[0]
    # a junction conflict 20 m ahead: a road user 2 s from it is given way to, one 9 s away not
    obs[[names.index("give_way_gap"), names.index("give_way_time")]] = (20.0, 2.0)
    assert pol.rule.accel(obs[None])[0] == pytest.approx(-10.0 ** 2 / (2 * (20.0 - p.s0)))
    obs[names.index("give_way_time")] = 9.0
    assert pol.act({"a": obs})["a"][0] == free[0]
    # speed limits: 10 m/s on a 30 km/h road brakes; a 30 km/h limit 40 m ahead of a 50 km/h
    # road leaves a desired speed of sqrt(8.33² + 2·b·40) (above 10: still accelerating),
    # 5 m ahead sqrt(8.33² + 2·b·5) (below 10: braking); unknown (0): the default v0
    lim = [names.index(n) for n in ("speed_limit", "speed_limit_ahead", "speed_limit_gap")]
    obs[lim] = (8.33, 8.33, 0.0)
    assert pol.rule.accel(obs[None])[0] < 0
    obs[lim] = (13.89, 8.33, 40.0)
    assert 0 < pol.rule.accel(obs[None])[0] < pol.rule.accel(
        np.where(np.isin(np.arange(obs.size), lim), 0, obs)[None])[0]
    obs[lim] = (13.89, 8.33, 5.0)
    assert pol.rule.accel(obs[None])[0] < 0
    obs[lim] = 0.0
    assert pol.act({"a": obs})["a"][0] == free[0]


def test_idm_agents_are_a_population_of_desired_speeds():
    """Each agent's desired speed is the rule's times its own factor (mean 1, deviation 0.1,
    cut at 0.8 and 1.2, as SUMO's speedFactor): fixed per agent and seed, another population
    after a reseed; on a free road a faster driver accelerates harder; deviation 0: the rule."""
    from magail_sumo.agents.idm import IdmPolicy
    from magail_sumo.sensors.observation import observation_names

    pol = IdmPolicy(0)
    f = np.array([pol.speed_factor(f"car{i}") for i in range(3000)])
    assert abs(f.mean() - 1.0) < 0.01 and 0.09 < f.std() < 0.11
    assert f.min() >= 0.8 and f.max() <= 1.2
    assert pol.speed_factor("car7") == IdmPolicy(0).speed_factor("car7")
    pol.reseed(1)
    assert pol.speed_factor("car7") != f[7]
    names = observation_names(pol.observation)
    obs = np.zeros(len(names), np.float32)
    obs[names.index("speed")] = 12.0
    obs[[names.index("leader_gap"), names.index("path_leader_gap")]] = 50.0  # none
    obs[names.index("light_gap")] = 50.0
    obs[[names.index("give_way_gap"), names.index("give_way_time")]] = (50.0, 10.0)
    obs[[names.index(f"route_x_{d:g}") for d in (5, 10, 20)]] = (5.0, 10.0, 20.0)
    slow, fast = sorted(((pol.speed_factor(n), n) for n in ("a", "b", "c", "d")))[::3]
    act = pol.act({slow[1]: obs, fast[1]: obs})
    assert act[fast[1]][0] > act[slow[1]][0]
    same = IdmPolicy(0, speed_dev=0.0).act({"a": obs, "b": obs})
    assert same["a"][0] == same["b"][0] == pytest.approx(float(pol.rule(obs[None])[0, 0]))


@pytest.mark.sumo
@pytest.mark.parametrize("speed_limits", [False, True])
def test_idm_route_follower_completes_trips_in_a_real_city(speed_limits):
    """The IDM route follower (``--policy idm``) on the real cologne8 city for 60 s: agents
    arrive at their routes' ends; collisions and red-light runs are rare; they read SUMO's
    lane speed limits (cologne8 has 30 and 50 km/h roads) and keep to them, each agent
    times its own desired-speed factor, with ``speed_limits``."""
    from magail_sumo.agents import env_settings
    from magail_sumo.sensors.observation import observation_names
    from magail_sumo.env.city_env import CityEnvConfig, SumoCityEnv
    from magail_sumo.env.config import EnvConfig
    from magail_sumo.agents.idm import IdmPolicy
    from magail_sumo.policies import make_policy

    pol = IdmPolicy(0, speed_limits=True) if speed_limits else make_policy("idm", 0)
    cfg = CityEnvConfig.from_env(EnvConfig(**env_settings(pol)), max_agents=40,
                                 control_fraction=1.0, warmup_s=300, max_steps=600)
    env = SumoCityEnv(ROOT / "data" / "sumo" / "cologne8" / "cologne8.sumocfg", cfg)
    reasons = collections.Counter()
    names = observation_names(pol.observation)
    limit = names.index("speed_limit") if speed_limits else None
    read = fast = 0
    lane_speeds = []
    try:
        obs, _ = env.reset(seed=0)
        api = env._session.api
        for t in range(600):
            obs, _, term, trunc, info = env.step(pol.act(obs))
            for name in term:
                if term[name] or trunc[name]:
                    reasons[info[name]["reason"]] += 1
            if speed_limits and t % 50 == 49:  # the limit read is the SUMO lane's; kept to
                running = set(api.vehicle.getIDList())
                for name, o in obs.items():
                    lane = api.vehicle.getLaneID(name) if name in running else ""
                    if lane and not lane.startswith(":"):
                        lane_speeds.append(api.lane.getMaxSpeed(lane))
                        read += abs(o[limit] - lane_speeds[-1]) < 0.01
                        fast += o[0] > lane_speeds[-1] * pol.speed_factor(name) + 0.5
    finally:
        env.close()
    if speed_limits:
        assert read >= 0.95 * len(lane_speeds) and fast == 0, (read, fast, len(lane_speeds))
        assert min(lane_speeds) < 9.0 < 13.0 < max(lane_speeds)  # 30 and 50 km/h roads both
    agents = sum(reasons.values())
    assert reasons["destination"] + reasons["arrived"] >= 10, reasons
    assert reasons["collision"] + reasons["red_light"] <= 0.1 * agents, reasons
    assert reasons["red_light"] <= 0.02 * agents, reasons  # it reads the stop line
