"""Rollouts Parquet files as the report reads them (``storage.read_rollouts_valid``): the
arrays and the valid mask back from a written file in any row order, and one-line errors
naming the file and the problem for a file that cannot be used."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from conftest import WOMD_DIR
from converters import load_scene
from magail_sumo.evaluation import methods, storage
from magail_sumo.evaluation.protocol import EvaluationError

SID = "850c48d8bbfa008f"


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    scene = load_scene(WOMD_DIR / f"{SID}.tfrecord")
    ro = methods.simulate(scene, "constvel", range(3))
    frame = storage.to_frame(scene, ro, "constvel")
    path = tmp_path_factory.mktemp("rollouts") / f"{SID}.parquet"
    storage.write_parquet(path, frame)
    return scene, ro, frame, path


def test_a_written_file_reads_back_in_any_row_order(written, tmp_path):
    scene, ro, frame, path = written
    got, valid = storage.read_rollouts_valid(path, scene)
    assert valid is None and np.array_equal(got.object_id, ro.object_id)
    for name in ("x", "y", "z", "heading"):
        assert np.array_equal(getattr(got, name), getattr(ro, name).astype(np.float32))
    shuffled = frame.sample(frac=1.0, random_state=0).copy()
    fut = shuffled["step"] > scene.current_time_index
    off = fut & (shuffled["object_id"] == ro.object_id[0]) & (shuffled["rollout"] == 1)
    shuffled.loc[off, "valid"] = False
    storage.write_parquet(tmp_path / "s.parquet", shuffled)
    again, mask = storage.read_rollouts_valid(tmp_path / "s.parquet", scene)
    assert np.array_equal(again.x, got.x) and np.array_equal(again.heading, got.heading)
    want = np.ones(ro.shape, bool)
    want[1, 0] = False
    assert np.array_equal(mask, want)


@pytest.mark.parametrize("damage, message", [
    (lambda f: f.drop(columns=["heading"]), "missing column(s) heading"),
    (lambda f: f.assign(scenario_id="another"), "holds scenario(s) another, expected " + SID),
    (lambda f: f.drop(index=f.index[-1]), "rows in"),
    (lambda f: f[f["step"] <= 10], "has no simulated steps"),
])
def test_a_damaged_file_is_refused_in_one_line(written, tmp_path, damage, message):
    scene, _, frame, _ = written
    path = tmp_path / f"{SID}.parquet"
    storage.write_parquet(path, damage(frame.copy()))
    with pytest.raises(EvaluationError) as err:
        storage.read_rollouts_valid(path, scene)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_a_file_that_is_not_parquet_is_named(written, tmp_path):
    scene = written[0]
    path = tmp_path / f"{SID}.parquet"
    path.write_text("not a table")
    with pytest.raises(EvaluationError, match=r"unreadable Parquet \(ArrowInvalid\)"):
        storage.read_rollouts_valid(path, scene)
    pd.DataFrame({"x": [1.0]}).to_parquet(path)
    with pytest.raises(EvaluationError, match=f"{path}: missing column"):
        storage.read_rollouts_valid(path, scene)
