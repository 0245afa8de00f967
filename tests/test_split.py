"""The generalisation protocol's split file (configs/splits/womd14.yaml) and its loader."""

from __future__ import annotations

import pytest

from conftest import ROOT
from converters import iter_scenes
from magail_sumo.config import ConfigError
from magail_sumo.splits import load_split

WOMD14 = ROOT / "configs" / "splits" / "womd14.yaml"
TEST_IDS = {"49c341dce1f65cdb", "53e9adfdac0eb822", "eb4b91b10ca94ff2", "8799c31b5be1f312"}


def test_womd14_split():
    split = load_split(WOMD14)
    train, test = split.files("train", ROOT), split.files("test", ROOT)
    assert len(train) == 10 and len(test) == 4
    ids = {p: [s.scenario_id for s in iter_scenes(p)] for p in train + test}
    assert all(len(v) == 1 for v in ids.values())  # one real WOMD scene per file
    assert {ids[p][0] for p in test} == TEST_IDS
    assert {ids[p][0] for p in train} == {
        "637f20cafde22ff8", "2831b6fde0420b0d", "850c48d8bbfa008f", "250011f460de6135",
        "2a1e44d405a6833f", "4d320edc9cb801a3", "61fa872f2d274223", "6f85f27e0243fc10",
        "7b24d74b506c94ce", "b36a6d0bc9e525bc"}
    # every bundled WOMD scene is in exactly one part
    bundled = sorted((ROOT / "data" / "womd").glob("*.tfrecord")) + [
        p for p in sorted((ROOT / "data" / "scenarionet").glob("*.pkl"))
        if not p.name.startswith("sd_nuscenes")]
    assert sorted(map(str, bundled)) == sorted(map(str, train + test))


@pytest.mark.parametrize("text,problem", [
    ("train: [a.pkl]\ntest: [b.pkl]\nval: [c.pkl]\n", r"val: unknown key"),
    ("train: [a.pkl]\ntest: []\n", r"test: needs at least one scene file"),
    ("train: [a.pkl, ./a.pkl]\ntest: [b.pkl]\n", r"train: a.pkl is listed twice"),
    ("train: [data/a.pkl]\ntest: [data/./a.pkl]\n", r"test: data/./a.pkl is also a training"),
    ("train: [data/womd/x.tfrecord]\ntest: [data/scenarionet/x.pkl]\n",
     r"test: data/scenarionet/x.pkl is the same scene as training file data/womd/x.tfrecord"),
    ("train: [a.pkl]\ntrain: [b.pkl]\ntest: [c.pkl]\n", r"duplicate key 'train'"),
    ("train: a.pkl\ntest: [b.pkl]\n", r"train: expected a list"),
])
def test_bad_split_files_are_refused(tmp_path, text, problem):
    path = tmp_path / "split.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=problem) as err:
        load_split(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_missing_scene_file_named(tmp_path):
    path = tmp_path / "split.yaml"
    path.write_text("train: [a.pkl]\ntest: [b.pkl]\n")
    split = load_split(path)
    with pytest.raises(ConfigError, match=r"split test\[0\]: b.pkl: no such file"):
        split.files("test", tmp_path)
