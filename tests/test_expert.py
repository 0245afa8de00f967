"""Expert demonstrations: recording through the env sensors, Parquet + metadata, sampling,
scenes that fail; the hash of the whole observation config (sensor ranges, not only the
layout's names) recorded with the data, and training refusing data recorded with another
config (data recorded before the hash is still read with the name-based layout check)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest

from conftest import WOMD_DIR
from magail_sumo.cli.main import main
from magail_sumo.config import from_dict
from magail_sumo.expert import ExpertDataError, ExpertDataset, observation_hash
from magail_sumo.sensors.config import BeamSpec
from magail_sumo.sensors.observation import ObservationConfig, observation_names
from magail_sumo.training.algorithms import load_expert
from magail_sumo.training.config import TrainConfig

SID = "850c48d8bbfa008f"
SCENE = WOMD_DIR / f"{SID}.tfrecord"


@pytest.fixture(scope="module")
def expert_dir(tmp_path_factory, bundled_networks):
    root = tmp_path_factory.mktemp("expert")
    rc = main(["expert", str(WOMD_DIR / f"{SID}.tfrecord"), "--out", str(root / "expert"),
               "--networks", str(bundled_networks(SID))])
    assert rc == 0
    return root / "expert"


@pytest.mark.sumo
def test_files_and_columns(expert_dir):
    meta = json.loads((expert_dir / "metadata.json").read_text())
    assert meta["observation_names"] == observation_names()
    assert meta["scenes"][0]["scenario_id"] == SID and meta["scenes"][0]["rows"] > 0
    table = pq.read_table(expert_dir / f"{SID}.parquet")
    assert set(table.column_names) >= {"scene_id", "track_id", "step", "done", "s", "s_next",
                                       "action", "accel", "steer"}
    assert table.num_rows == meta["scenes"][0]["rows"]


@pytest.mark.sumo
def test_transitions_chain_and_actions_are_policy_scaled(expert_dir):
    ds = ExpertDataset(expert_dir, observation_names())
    names = ds.observation_names
    pa, ps = names.index("prev_accel"), names.index("prev_steer")
    assert np.all(np.abs(ds.action) <= 1.0)
    np.testing.assert_array_equal(ds.s_next[:, [pa, ps]], ds.action)  # s' carries the action
    for track in np.unique(ds.track):  # s of step t+1 is s' of step t (same vehicle)
        rows = np.flatnonzero(ds.track == track)
        rows = rows[np.argsort(ds.step[rows])]
        steps = ds.step[rows]
        consecutive = np.flatnonzero(np.diff(steps) == 1)
        np.testing.assert_allclose(ds.s[rows[consecutive + 1]], ds.s_next[rows[consecutive]],
                                   atol=1e-6)
        assert ds.done[rows[-1]] and not ds.done[rows[:-1]].any()


@pytest.mark.sumo
def test_sampling(expert_dir):
    ds = ExpertDataset(expert_dir)
    rng = np.random.default_rng(0)
    batch = ds.sample_scene_steps(8, rng)
    assert batch.x.shape[0] == 8 and batch.x.shape[2] == 2 * ds.obs_dim
    assert batch.mask.any(axis=1).all() and np.all(batch.x[~batch.mask] == 0)
    s, a = ds.sample_pairs(16, rng)
    assert s.shape == (16, ds.obs_dim) and a.shape == (16, 2)


@pytest.mark.sumo
def test_bad_expert_dirs_are_refused(expert_dir, tmp_path):
    with pytest.raises(ExpertDataError, match="no metadata.json"):
        ExpertDataset(tmp_path)
    with pytest.raises(ExpertDataError, match="not found"):
        ExpertDataset(tmp_path / "missing")
    names = observation_names(ObservationConfig(layout="scene_frame"))
    with pytest.raises(ExpertDataError, match=r"layout mismatch.*108.*index 0.*'speed'.*'x'"):
        ExpertDataset(expert_dir, names)
    meta = json.loads((expert_dir / "metadata.json").read_text())
    meta["scenes"] = []
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(ExpertDataError, match="no transitions"):
        ExpertDataset(empty)


# ----------------------------------------------------------------------------------- failing scenes
def test_expert_goes_on_past_failing_scenes(tmp_path):
    from magail_sumo.env.vec_env import SceneSpec
    from magail_sumo.expert import record_expert

    specs = [SceneSpec(str(SCENE), str(tmp_path / "no-bundle"), SID),
             SceneSpec(str(SCENE), str(tmp_path / "no-bundle"), "no-such-scene")]
    seen = []
    meta = record_expert(specs, tmp_path / "expert", on_error=lambda s, r: seen.append(r),
                         timeout_s=120)
    assert meta["scenes"] == [] and len(meta["failed"]) == 2 and len(seen) == 2
    assert all("\n" not in r for r in seen)
    assert "no-such-scene" in seen[1]


# -------------------------------------------------------------------- the observation config's hash
LONGER = ObservationConfig(lidar=BeamSpec(80, 40.0))


def test_the_hash_covers_every_field():
    assert observation_hash(ObservationConfig()) == observation_hash(ObservationConfig())
    assert observation_names(LONGER) == observation_names(ObservationConfig())
    assert observation_hash(LONGER) != observation_hash(ObservationConfig())
    assert observation_hash(ObservationConfig(leader_range=60.0)) != \
        observation_hash(ObservationConfig())


@pytest.mark.sumo
def test_training_refuses_expert_data_of_another_observation_config(expert_dir, tmp_path):
    meta = json.loads((expert_dir / "metadata.json").read_text())
    assert meta["observation_hash"] == observation_hash(ObservationConfig())
    assert len(ExpertDataset(expert_dir, observation=ObservationConfig())) > 0
    with pytest.raises(ExpertDataError) as err:
        ExpertDataset(expert_dir, observation=LONGER)
    msg = str(err.value)
    assert "\n" not in msg and str(expert_dir) in msg
    assert "observation.lidar.range: expert 30.0, training 40.0" in msg
    assert "observation.lidar.beams" not in msg  # only the fields that differ

    cfg = from_dict(TrainConfig, {"expert_dir": str(expert_dir),
                                  "env": {"observation": {"lidar": {"beams": 80,
                                                                    "range": 40.0}}}})
    with pytest.raises(ExpertDataError, match=r"lidar\.range: expert 30\.0, training 40\.0"):
        load_expert(cfg)
    same = from_dict(TrainConfig, {"expert_dir": str(expert_dir)})
    assert load_expert(same).obs_dim == len(observation_names())


@pytest.mark.sumo
def test_expert_data_recorded_before_a_field_was_added_reads_it_as_its_default(expert_dir,
                                                                              tmp_path):
    """Data whose recorded observation config lacks a field added since (its hash was of the
    fields of then) trains a config that leaves that field at its default, not one that sets
    it."""
    old = tmp_path / "before"
    shutil.copytree(expert_dir, old)
    meta = json.loads((old / "metadata.json").read_text())
    del meta["observation"]["speed_limit"]
    meta["observation_hash"] = "0" * 64  # the hash of the fields of then
    (old / "metadata.json").write_text(json.dumps(meta))
    assert len(ExpertDataset(old, observation=ObservationConfig())) > 0
    with pytest.raises(ExpertDataError, match="speed_limit"):
        ExpertDataset(old, observation=ObservationConfig(speed_limit=True))


@pytest.mark.sumo
def test_expert_data_without_the_hash_is_checked_by_names(expert_dir, tmp_path):
    old = tmp_path / "old"
    shutil.copytree(expert_dir, old)
    meta = json.loads((old / "metadata.json").read_text())
    del meta["observation_hash"]
    (old / "metadata.json").write_text(json.dumps(meta))
    assert len(ExpertDataset(old, observation=LONGER)) > 0  # same names: accepted as before
    with pytest.raises(ExpertDataError, match="layout mismatch"):
        ExpertDataset(old, observation=ObservationConfig(leader=True))
