"""Expert data records a hash of its whole observation config (sensor ranges, not only the
layout's names), and training refuses data recorded with another config; data recorded before
the hash is still read with the name-based layout check."""

from __future__ import annotations

import json
import shutil

import pytest

from conftest import WOMD_DIR
from magail_sumo.cli.main import main
from magail_sumo.config import from_dict
from magail_sumo.expert import ExpertDataError, ExpertDataset, observation_hash
from magail_sumo.sensors.config import BeamSpec, ObservationConfig
from magail_sumo.sensors.observation import observation_names
from magail_sumo.training.algorithms import load_expert
from magail_sumo.training.config import TrainConfig

SID = "850c48d8bbfa008f"
#: the default observation with a longer lidar: the same layout (names), other values
LONGER = ObservationConfig(lidar=BeamSpec(80, 40.0))


@pytest.fixture(scope="module")
def expert_dir(tmp_path_factory, bundled_networks):
    root = tmp_path_factory.mktemp("expert")
    rc = main(["expert", str(WOMD_DIR / f"{SID}.tfrecord"), "--out", str(root / "expert"),
               "--networks", str(bundled_networks(SID))])
    assert rc == 0
    return root / "expert"


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
def test_expert_data_without_the_hash_is_checked_by_names(expert_dir, tmp_path):
    old = tmp_path / "old"
    shutil.copytree(expert_dir, old)
    meta = json.loads((old / "metadata.json").read_text())
    del meta["observation_hash"]
    (old / "metadata.json").write_text(json.dumps(meta))
    assert len(ExpertDataset(old, observation=LONGER)) > 0  # same names: accepted as before
    with pytest.raises(ExpertDataError, match="layout mismatch"):
        ExpertDataset(old, observation=ObservationConfig(leader=True))
