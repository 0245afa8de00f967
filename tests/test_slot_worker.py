"""The scene worker on a recorded scene's array API gives exactly the packets of its dict API
(slots, observations, poses, dones, terminal observations, reasons, events, episode resets), on
every real WOMD and ScenarioNet scene in data/, in training-like configs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magail_sumo.env import EnvConfig
from magail_sumo.env.guard import GuardConfig
from magail_sumo.env.slot_worker import SceneSpec, SlotWorker
from magail_sumo.sensors.config import ObservationConfig

ROOT = Path(__file__).resolve().parents[1]
SCENES = sorted((ROOT / "data" / "womd").glob("*.tfrecord")) + \
    sorted((ROOT / "data" / "scenarionet").glob("*.pkl"))

CONFIGS = {
    # the womd14 recipe's episodes: random windows, collision and off-road end an agent
    "recipe": EnvConfig(start_window="random", max_steps=40, sumo_mirror=False,
                        terminate_on=("collision", "off_road")),
    # every event ends an agent, guard, leader, route command and look-ahead, route-relative
    # control, the road-edge rule
    "training": EnvConfig(start_window="random", max_steps=40, sumo_mirror=False,
                          action_layout="accel_offset", off_road_rule="road_edge",
                          guard=GuardConfig(kind="gap"),
                          observation=ObservationConfig(command=True,
                                                        route_points=(10.0, 30.0),
                                                        leader=True)),
}


def actions(rng: np.random.Generator, slots: int) -> np.ndarray:
    """Random actions that brake hard now and then (agents collide and leave the road)."""
    a = rng.uniform(-1, 1, (slots, 2)).astype(np.float32)
    a[rng.random(slots) < 0.2, 0] = -1.0
    return a


def same_packet(a: dict, b: dict, where: str) -> None:
    assert sorted(a) == sorted(b), where
    for key in a:
        if isinstance(a[key], np.ndarray):
            np.testing.assert_array_equal(a[key], b[key], err_msg=f"{where}: {key}")
            assert a[key].dtype == b[key].dtype, f"{where}: {key}"
        elif key == "infos":
            assert sorted(a[key]) == sorted(b[key]), where
            for k, ia in a[key].items():
                ib = b[key][k]
                assert sorted(ia) == sorted(ib), where
                np.testing.assert_array_equal(ia["terminal_observation"],
                                              ib["terminal_observation"], err_msg=where)
                assert {n: v for n, v in ia.items() if n != "terminal_observation"} == \
                    {n: v for n, v in ib.items() if n != "terminal_observation"}, where
        else:
            assert a[key] == b[key], f"{where}: {key}"


@pytest.mark.parametrize("config", sorted(CONFIGS))
@pytest.mark.parametrize("scene_file", SCENES, ids=lambda p: p.stem)
def test_array_worker_packets_equal_the_dict_worker(scene_file, config, bundled_networks,
                                                    monkeypatch):
    spec = SceneSpec(str(scene_file), str(bundled_networks.bundle(scene_file.stem)))
    cfg = CONFIGS[config]
    fast = SlotWorker(spec, cfg, seed=7, slots=None)
    slow = SlotWorker(spec, cfg, seed=7, slots=None)
    monkeypatch.setattr(slow, "_uses_arrays", lambda: False)
    try:
        same_packet(fast.reset(), slow.reset(), "reset")
        assert fast.arrays and not slow.arrays
        rng = np.random.default_rng(3)
        ended, episodes = 0, 0
        for t in range(160):
            act = actions(rng, fast.slots)
            a, b = fast.step(act), slow.step(act)
            same_packet(a, b, f"step {t}")
            ended += len(a["infos"])
            episodes += a["episodes"]
        assert ended > 0 and episodes >= 2  # agents left and episodes were reset
    finally:
        fast.close()
        slow.close()


def test_array_worker_runs_the_log_on_as_the_dict_worker(bundled_networks, monkeypatch):
    """A step that leaves nobody live while others are still to join: both workers run the
    log on to the next joiner within the same step, packet for packet (every agent swerves
    off the road at once; later tracks of the log join after)."""
    scene_file = next((ROOT / "data" / "scenarionet").glob("*0757*.pkl"))  # nuScenes
    spec = SceneSpec(str(scene_file), str(bundled_networks.bundle(scene_file.stem)))
    cfg = EnvConfig(start_window="random", max_steps=80, sumo_mirror=False,
                    terminate_on=("collision", "off_road"))
    fast = SlotWorker(spec, cfg, seed=1, slots=None)
    slow = SlotWorker(spec, cfg, seed=1, slots=None)
    monkeypatch.setattr(slow, "_uses_arrays", lambda: False)
    joined_late: list[int] = []
    run_on = fast.env.run_on_arrays

    def counted():
        late = run_on()
        joined_late.append(int(late.size))
        return late

    monkeypatch.setattr(fast.env, "run_on_arrays", counted)
    try:
        same_packet(fast.reset(), slow.reset(), "reset")
        swerve = np.tile(np.array([[1.0, 1.0]], np.float32), (fast.slots, 1))
        for t in range(300):
            same_packet(fast.step(swerve), slow.step(swerve), f"step {t}")
    finally:
        fast.close()
        slow.close()
    assert any(n > 0 for n in joined_late), f"no late joiner after an empty step: {joined_late}"
