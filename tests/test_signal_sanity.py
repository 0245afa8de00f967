"""Traffic-light sanity of recorded scenes: logged red-light running, signal gaps, UNKNOWN runs."""

from __future__ import annotations

import numpy as np
import pytest

from magail_sumo.scene.signal_sanity import longest_run, signal_sanity
from magail_sumo.scene import Lane, ObjectType, RoadMap, Scene, SignalStates, Tracks
from magail_sumo.scene.types import LaneType, SignalState

S, U, G = int(SignalState.STOP), int(SignalState.UNKNOWN), int(SignalState.GO)


def _scene() -> Scene:
    """Approach lane 1 (0..50 m along +x) into junction lane 2 (50..70 m), whose signal has its
    stop point at x = 50. Track 10 (vehicle) crosses it at step 8 on red; track 11 (vehicle) at
    step 5 while the state is UNKNOWN; track 12 (pedestrian) like 10. Lane 2 has no record at
    step 4 and UNKNOWN at 5-6; lane 3 has records at steps 0 and 9 only."""
    t_n = 10
    steps = np.arange(t_n)
    x = np.stack([31 + 2.5 * steps, 38.5 + 2.5 * steps, 31 + 2.5 * steps])
    n = len(x)
    z = np.zeros((n, t_n))
    tracks = Tracks(id=[10, 11, 12], type=[ObjectType.VEHICLE, ObjectType.VEHICLE,
                                           ObjectType.PEDESTRIAN],
                    x=x, y=z, z=z, length=z + 4, width=z + 2, height=z + 1.5, heading=z,
                    vx=z + 25, vy=z, valid=np.ones((n, t_n), bool))
    pts = lambda a, b: np.array([[a, 0.0, 0.0], [b, 0.0, 0.0]])  # noqa: E731
    lanes = (Lane(1, pts(0, 50), LaneType.SURFACE_STREET, exit_lanes=(2,)),
             Lane(2, pts(50, 70), LaneType.SURFACE_STREET, entry_lanes=(1,)),
             Lane(3, np.array([[50, 10, 0], [70, 10, 0.0]]), LaneType.SURFACE_STREET))
    lane2 = {0: S, 1: S, 2: S, 3: S, 5: U, 6: U, 7: S, 8: S, 9: S}
    recs = sorted([(t, 2, s) for t, s in lane2.items()] + [(0, 3, G), (9, 3, G)])
    step, lane, state = (np.array(v) for v in zip(*recs))
    stop = np.array([[50.0, 0.0, 0.0] if ln == 2 else [50.0, 10.0, 0.0] for ln in lane])
    return Scene("constructed", steps * 0.1, tracks, RoadMap(lanes=lanes),
                 SignalStates(step, lane, state, stop))


def test_longest_run():
    m = np.array([[1, 0], [1, 0], [0, 1], [1, 1], [1, 1], [1, 0]], bool)
    assert longest_run(m).tolist() == [3, 3]
    assert longest_run(np.zeros((0, 2), bool)).tolist() == [0, 0]


def test_constructed_red_light_run_gap_and_unknown():
    rep = signal_sanity(_scene())
    assert rep["signal_lanes"] == 2 and rep["records"] == 11
    assert rep["red_light_runs"] == {"events": 1, "vehicles": 1,
                                     "listed": [{"track_id": 10, "step": 8}]}
    assert rep["gaps"] == {"steps": 9, "lanes": 2, "longest": 8}
    assert rep["unknown"] == {"steps": 2, "lanes": 1, "longest": 2}
    lane2, lane3 = rep["lanes"]
    assert lane2 == {"lane": 2, "records": 9, "first_step": 0, "last_step": 9, "gap_steps": 1,
                     "longest_gap": 1, "unknown_steps": 2, "longest_unknown": 2}
    assert (lane3["gap_steps"], lane3["longest_gap"], lane3["unknown_steps"]) == (8, 8, 0)


def test_no_signals_is_all_zero(scene_637f):
    import dataclasses

    rep = signal_sanity(dataclasses.replace(scene_637f, signals=SignalStates.empty()))
    assert rep["signal_lanes"] == 0 and rep["red_light_runs"]["events"] == 0
    assert rep["gaps"]["steps"] == 0 and rep["lanes"] == []


@pytest.mark.sumo
def test_bundled_scene_and_conversion_report(scene_637f, tmp_path):
    from converters.sumo.scenario import ConvertOptions, convert_scene

    rep = signal_sanity(scene_637f)
    assert (rep["signal_lanes"], rep["records"]) == (12, 1092)
    assert rep["red_light_runs"]["events"] == 0 and rep["gaps"]["steps"] == 0
    assert rep["unknown"] == {"steps": 540, "lanes": 12, "longest": 91}
    assert sum(ln["records"] for ln in rep["lanes"]) == 1092
    conv = convert_scene(scene_637f, tmp_path, ConvertOptions(baseline=False))
    assert conv.status == "ok"
    assert conv.to_dict()["data_quality"]["signals"] == rep


def test_a_failing_check_is_reported_not_raised(monkeypatch):
    import magail_sumo.scene.signal_sanity as mod

    def boom(scene):
        raise ValueError("odd\ndata")

    monkeypatch.setattr(mod, "signal_sanity", boom)
    rep = mod.checked_signal_sanity(_scene())
    assert rep == {"error": "ValueError: odd data"}
    assert mod.format_signal_sanity(rep) == "not checked (ValueError: odd data)"
