"""Expert demonstrations: recording through the env sensors, Parquet + metadata, sampling."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from conftest import WOMD_DIR
from magail_sumo.cli.main import main
from magail_sumo.env.scene_specs import scene_specs
from magail_sumo.expert import ExpertDataError, ExpertDataset
from magail_sumo.sensors.observation import ObservationConfig, observation_names

SID = "850c48d8bbfa008f"


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
