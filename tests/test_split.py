"""The generalisation protocol's split file (configs/splits/womd14.yaml) and its loader."""

from __future__ import annotations

import os

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


WILD = ROOT / "configs" / "splits" / "wild.yaml"


def test_data_root_reads_the_environment_the_shell_way(tmp_path, monkeypatch):
    (tmp_path / "d").mkdir()
    for name in ("a.pkl", "b.pkl"):
        (tmp_path / "d" / name).write_bytes(b"")
    path = tmp_path / "split.yaml"
    path.write_text("data_root: ${SPLIT_TEST_ROOT:-d}\ntrain: [a.pkl]\ntest: [b.pkl]\n")
    monkeypatch.delenv("SPLIT_TEST_ROOT", raising=False)
    split = load_split(path)
    assert split.files("test", tmp_path) == [tmp_path / "d" / "b.pkl"]
    monkeypatch.setenv("SPLIT_TEST_ROOT", str(tmp_path / "elsewhere"))
    assert split.paths("train", tmp_path) == [tmp_path / "elsewhere" / "a.pkl"]
    with pytest.raises(ConfigError, match=r"split train\[0\]: a.pkl: no such file \(under "
                       + str(tmp_path / "elsewhere")):
        split.files("train", tmp_path)
    # a missing file in a subfolder names the data root it was looked for under
    path.write_text("data_root: d\ntrain: [a.pkl]\ntest: [sub/b.pkl]\n")
    with pytest.raises(ConfigError, match=r"split test\[0\]: sub/b.pkl: no such file \(under "
                       + str(tmp_path / "d") + r"\)$"):
        load_split(path).files("test", tmp_path)
    monkeypatch.delenv("SPLIT_TEST_ROOT")
    for text, problem in (
            ("${SPLIT_TEST_ROOT}", "environment variable SPLIT_TEST_ROOT is not set"),
            ("$HOME/x", "only \\$\\{NAME\\} and \\$\\{NAME:-default\\} are expanded")):
        path.write_text(f"data_root: {text!r}\ntrain: [a.pkl]\ntest: [b.pkl]\n")
        with pytest.raises(ConfigError, match=problem) as err:
            load_split(path)
        assert "data_root" in str(err.value) and "\n" not in str(err.value)


def test_wild_split_at_the_scale_of_the_shared_data():
    split = load_split(WILD)
    assert len(split.train) == 73 and len(split.test) == 32
    womd_test = [f for f in split.test if "nuscenes" not in f]
    assert len(womd_test) >= 20 and len(split.train) >= 50
    assert any("nuscenes" in f for f in split.train) and any("nuscenes" in f for f in split.test)
    # the old split's test scenes stay test scenes, its train scenes train scenes
    old = load_split(WOMD14)
    stems = lambda files: {os.path.basename(f).split(".")[0] for f in files}  # noqa: E731
    assert stems(old.test) <= stems(split.test) and stems(old.train) <= stems(split.train)
    root = split.paths("test", ROOT)[0].parents[2]
    if not root.is_dir():
        pytest.skip(f"{root}: the shared data is not on this machine")
    train, test = split.files("train", ROOT), split.files("test", ROOT)
    ids = {p: [s.scenario_id for s in iter_scenes(p)] for p in train + test}
    assert all(len(v) == 1 for v in ids.values())
    assert not {ids[p][0] for p in train} & {ids[p][0] for p in test}
