"""Road-edge off-road rule (``env.off_road_rule: road_edge``): WOSAC's off-road test in the env,
relative to the log, on real scenes."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR

SID = "637f20cafde22ff8"


def _scene():
    from converters import load_scene

    return load_scene(WOMD_DIR / f"{SID}.tfrecord")


def test_the_log_is_never_off_road_by_its_own_standard():
    """Recorded poses: the corner test agrees with the stored log flags, some parked vehicles
    stand off the road in the log, and none of the log is off-road relative to itself."""
    from magail_sumo.env.driving_env import _median_valid
    from magail_sumo.env.events import RoadEdgeRule

    scene = _scene()
    tr = scene.tracks
    length, width = _median_valid(tr.length, tr.valid), _median_valid(tr.width, tr.valid)
    rule = RoadEdgeRule.build(scene, 0.0, length, width)
    r, t = np.nonzero(tr.valid)
    args = (tr.x[r, t], tr.y[r, t], tr.heading[r, t], length[r], width[r])
    corners = rule.corners_off(r, *args)
    assert np.array_equal(corners, rule.log_off[r, t])
    assert corners.any() and not corners.all()
    for step in range(0, tr.valid.shape[1], 7):  # step by step, as the env calls it
        k = np.flatnonzero(tr.valid[:, step])
        assert not rule.off_road(k, step, tr.x[k, step], tr.y[k, step], tr.heading[k, step],
                                 length[k], width[k]).any()
    # a vehicle moved 30 m sideways from an on-road pose is off the road (and on a map without
    # road edges there is no rule: the env keeps the lane rule)
    on = np.flatnonzero(~corners & (tr.type[r] == 1))
    k, s = r[on[0]], t[on[0]]
    shifted = [rule.off_road(np.array([k]), int(s), np.array([tr.x[k, s] + dx]),
                             np.array([tr.y[k, s] + dy]), np.array([tr.heading[k, s]]),
                             length[[k]], width[[k]])[0]
               for dx, dy in ((30, 0), (-30, 0), (0, 30), (0, -30))]
    assert any(shifted)
    from converters import load_scene

    nusc = load_scene(ROOT / "data" / "scenarionet" / "sd_nuscenes_v1.0-mini_scene-0757.pkl")
    assert RoadEdgeRule.build(nusc, 0.0, np.ones(len(nusc.tracks.id)),
                              np.ones(len(nusc.tracks.id))) is None


def _off_road_agents(rule: str, steer: float | None, episodes: int = 2, margin: float = 0.0
                     ) -> tuple[int, int]:
    """(agents flagged off-road, agents) over ``episodes`` random windows of the scene, the
    agents replaying the log (``steer`` None) or driving with a fixed steering at 0.3 throttle."""
    from magail_sumo.env import REPLAY_LIMITS, EnvConfig, SumoDrivingEnv, expert_actions

    env = SumoDrivingEnv(_scene(), ROOT / "networks" / SID, EnvConfig(
        controlled="all", start_window="random", max_steps=60, terminate_on=(),
        sumo_mirror=False, off_road_rule=rule, off_road_edge_margin=margin,
        limits=REPLAY_LIMITS if steer is None else EnvConfig().limits))
    flagged, seen = set(), set()
    try:
        for ep in range(episodes):
            env.reset(seed=ep)
            while env.agents:
                act = expert_actions(env) if steer is None else \
                    {a: np.array([0.3, steer], np.float32) for a in env.agents}
                infos = env.step(act)[4]
                seen |= {(ep, a) for a in infos}
                flagged |= {(ep, a) for a, i in infos.items() if i["events"].get("off_road")}
    finally:
        env.close()
    return len(flagged), len(seen)


@pytest.mark.sumo
def test_road_edge_rule_spares_the_log_and_catches_leaving_the_road():
    """Replaying the log the road-edge rule flags few agents (those whose bicycle heading
    drifts from the recorded one by up to 0.25 rad while they skirt the edge), and nobody with
    0.5 m of tolerance; agents circling at full steering lock leave the road and are
    flagged."""
    edge, n = _off_road_agents("road_edge", None)
    tolerant, _ = _off_road_agents("road_edge", None, margin=0.5)
    assert n >= 40 and edge <= 0.06 * n and tolerant == 0, (edge, tolerant, n)
    circling, m = _off_road_agents("road_edge", 1.0, episodes=1)
    assert circling >= 0.3 * m, (circling, m)


def test_off_road_rule_refusal():
    from magail_sumo.config import ConfigError, from_dict
    from magail_sumo.env import EnvConfig

    with pytest.raises(ConfigError, match="off_road_rule"):
        from_dict(EnvConfig, {"off_road_rule": "kerb"})
    assert from_dict(EnvConfig, {"off_road_rule": "road_edge"}).off_road_rule == "road_edge"
