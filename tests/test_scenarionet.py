"""ScenarioNet reader/writer: round trips on real scenes, layout, and the restricted unpickler."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest

from converters import iter_scene_records, load_scene
from converters.scenarionet import (
    UnsafePickleError, load_scenarionet, safe_loads, scene_from_scenarionet,
    scene_to_scenarionet, write_scenarionet, write_scenarionet_dataset,
)
from converters.womd import write_womd
from magail_sumo.errors import SceneFormatError
from magail_sumo.scene import SceneValidationError


def test_womd_scenarionet_round_trip_all_real_scenes(tmp_path, real_scene):
    """WOMD -> Scene -> ScenarioNet pickle -> Scene -> WOMD -> Scene keeps every field."""
    path = write_scenarionet(tmp_path / "sd_waymo_v1.2_x.pkl", real_scene)
    back = load_scenarionet(path)
    assert back == real_scene, back.differences(real_scene)
    write_womd(tmp_path / "again.tfrecord", [back])
    assert load_scene(tmp_path / "again.tfrecord") == real_scene


def test_layout_matches_scenarionet_conventions(scene_637f):
    sd = scene_to_scenarionet(scene_637f)
    assert list(sd) == ["id", "version", "length", "tracks", "dynamic_map_states",
                        "map_features", "metadata"]
    assert sd["length"] == 91 and sd["version"] == "v1.2"
    key, track = next(iter(sd["tracks"].items()))
    assert isinstance(key, str) and track["metadata"]["object_id"] == key
    st = track["state"]
    assert st["position"].shape == (91, 3) and st["heading"].shape == (91,)
    assert st["velocity"].shape == (91, 2) and st["valid"].dtype == bool
    meta = sd["metadata"]
    assert meta["sdc_id"] == str(int(scene_637f.tracks.id[82])) and meta["ts"].shape == (91,)
    assert {"metadrive_processed", "coordinate", "ts"} <= set(meta)
    lane = sd["map_features"][str(scene_637f.roadmap.lanes[0].id)]
    assert lane["type"] == "LANE_SURFACE_STREET" and lane["polyline"].shape[1] == 3
    assert all(isinstance(v, int) for v in lane["entry_lanes"] + lane["exit_lanes"])
    light = next(iter(sd["dynamic_map_states"].values()))
    assert len(light["state"]["object_state"]) == 91 and light["stop_point"].shape == (3,)
    # every dict key is a str and no numpy scalar appears (MetaDrive's sanity_check rules)
    def walk(x):
        if isinstance(x, dict):
            for k, v in x.items():
                assert isinstance(k, str)
                walk(v)
        elif isinstance(x, list):
            for v in x:
                walk(v)
        else:
            assert isinstance(x, (int, float, str, np.ndarray, set, tuple, type(None))), type(x)
    walk(sd)


def test_reads_float32_numpy1_style_pickles(scene_637f):
    """Real ScenarioNet files: float32 arrays, protocol 2-4, numpy.core globals (numpy 1)."""
    sd = scene_to_scenarionet(scene_637f)
    for track in sd["tracks"].values():
        track["state"]["position"] = track["state"]["position"].astype(np.float32)
    data = pickle.dumps(sd, protocol=2).replace(b"cnumpy._core.multiarray\n", b"cnumpy.core.multiarray\n")
    assert b"cnumpy.core.multiarray\n_reconstruct" in data
    scene = scene_from_scenarionet(safe_loads(data))
    assert np.allclose(scene.tracks.x, scene_637f.tracks.x, atol=1e-2)
    assert scene.summary() == scene_637f.summary()


class _Exploit:
    def __reduce__(self):
        return (os.system, ("touch /tmp/magail_sumo_pwned",))


def test_pickle_with_arbitrary_class_is_refused(tmp_path):
    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"id": "x", "payload": _Exploit()}))
    with pytest.raises(UnsafePickleError, match="refused to load"):
        safe_loads(path.read_bytes())
    [rec] = list(iter_scene_records(path))
    assert not rec.ok and "evil.pkl: record 0: unsafe pickle, nothing executed: refused to load posix.system" in str(rec.error)
    assert not os.path.exists("/tmp/magail_sumo_pwned")


@pytest.mark.parametrize("mutate, message", [
    (lambda sd: sd["tracks"][next(iter(sd["tracks"]))]["state"].__setitem__("position", "oops"),
     r"state\.position: expected a numeric array"),
    (lambda sd: sd["tracks"][next(iter(sd["tracks"]))]["state"].__setitem__("heading", np.zeros(5)),
     r"state\.heading: expected shape \(91,\), got \(5,\)"),
    (lambda sd: sd.pop("map_features"), "missing key 'map_features'"),
    (lambda sd: sd["map_features"][next(iter(sd["map_features"]))].__setitem__("type", "HOVERCRAFT"),
     "unsupported map feature type 'HOVERCRAFT'"),
])
def test_wrong_typed_fields_are_named(tmp_path, scene_637f, mutate, message):
    sd = scene_to_scenarionet(scene_637f)
    mutate(sd)
    with pytest.raises(SceneValidationError, match=message):
        scene_from_scenarionet(sd)
    path = tmp_path / "bad.pkl"
    path.write_bytes(pickle.dumps(sd, protocol=4))
    with pytest.raises(SceneFormatError, match="bad.pkl: record 0: "):
        load_scenarionet(path)


def test_dataset_folder(tmp_path, real_scene):
    files = write_scenarionet_dataset(tmp_path / "ds", [real_scene])
    assert files[0].name == f"sd_waymo_v1.2_{real_scene.scenario_id}.pkl"
    [rec] = list(iter_scene_records(tmp_path / "ds"))
    assert rec.ok and rec.scene == real_scene
