"""The bundle layout (converters.sumo.bundle), find_scene, and SessionConfig options left to the
config; no SUMO run (the shipped bundle of the bundled scene is copied)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from converters import find_scene
from converters.sumo.bundle import (BundleError, BundleLayout, SceneBundle, bundle_folder,
                                    check_bundle, complete_bundle, is_bundle_dir)
from converters.sumo.scenario import ensure_bundle
from magail_sumo.errors import SceneFormatError
from magail_sumo.sim.session import SessionConfig, SumoSession

ROOT = Path(__file__).resolve().parents[1]
SID = "637f20cafde22ff8"
WOMD = ROOT / "data" / "womd"


@pytest.fixture()
def networks(tmp_path) -> Path:
    """A networks folder holding a copy of the shipped bundle of SID."""
    root = tmp_path / "nets"
    shutil.copytree(ROOT / "networks" / SID, root / SID)
    return root


def test_find_scene_by_id_first_and_missing():
    files = sorted(WOMD.glob("*.tfrecord"))
    assert find_scene(files, SID).scenario_id == SID
    assert find_scene(WOMD / f"{SID}.tfrecord", None).scenario_id == SID
    with pytest.raises(SceneFormatError, match=rf"{SID}\.tfrecord: scenario nope not found"):
        find_scene(WOMD / f"{SID}.tfrecord", "nope")


def test_layout_names_the_files(networks):
    files = BundleLayout.of(networks / SID, SID)
    assert [p.name for p in (files.net, files.routes, files.signals, files.sumocfg)] == \
        [f"{SID}.net.xml", f"{SID}.rou.xml", f"{SID}.tll.xml", f"{SID}.sumocfg"]
    assert files.report.name == "conversion.json" and is_bundle_dir(files.folder)
    assert bundle_folder(networks, SID) == files.folder
    report = check_bundle(files.folder, SID)
    assert report["status"] == "ok" and set(report["files"]) <= {p.name for p in
                                                                 files.folder.iterdir()}


def test_incomplete_bundles_are_refused(scene_637f, networks):
    folder = networks / SID
    assert complete_bundle(networks, SID) == folder
    assert SceneBundle.load(scene_637f, folder).files.signals.is_file()
    (folder / f"{SID}.nod.xml").unlink()  # a file the report lists
    with pytest.raises(BundleError, match=rf"{SID}\.nod\.xml: bundle file not found"):
        SceneBundle.load(scene_637f, folder)
    assert complete_bundle(networks, SID) is None
    report = json.loads((folder / "conversion.json").read_text())
    report["files"].remove(f"{SID}.nod.xml")
    for change, message in (({"status": "failed", "reason": "netconvert: boom"},
                             "conversion failed: netconvert: boom"),
                            ({"scenario_id": "other"}, "bundle of scenario other, not")):
        (folder / "conversion.json").write_text(json.dumps({**report, **change}))
        with pytest.raises(BundleError, match=message):
            check_bundle(folder, SID)
        assert complete_bundle(networks, SID) is None
    (folder / "conversion.json").write_text("{")
    with pytest.raises(BundleError, match="unreadable bundle file"):
        check_bundle(folder, SID)
    (folder / "conversion.json").write_text(json.dumps(report))
    assert complete_bundle(networks, SID) == folder


def test_ensure_bundle_finds_a_complete_one_without_converting(scene_637f, networks, tmp_path):
    into = tmp_path / "out" / "networks"
    assert ensure_bundle(scene_637f, into, search=[tmp_path / "none", networks],
                         claim=True) == networks / SID
    assert not into.exists()  # nothing claimed, locked or converted
    assert ensure_bundle(scene_637f, networks) == networks / SID
    assert not (networks / ".locks").exists()


def test_session_options_left_to_the_config(networks):
    """The configuration's behaviour options are kept (never ``-c``); the session's own
    options, when set, replace them."""
    cfg = BundleLayout.of(networks / SID, SID).sumocfg
    default = SumoSession(cfg).command()
    assert "-c" not in default and default[0] == "sumo"
    opts = dict(zip(default[1::2], default[2::2]))
    assert opts["--end"] == "9.1" and opts["--begin"] == "0"  # the configuration's
    assert opts["--step-length"] == "0.1" and opts["--seed"] == "0"  # the session's
    assert opts["--time-to-teleport"] == "-1" and opts["--collision.action"] == "warn"
    assert opts["--net-file"].endswith(f"{SID}.net.xml")
    bare = SessionConfig(step_length=None, seed=None, time_to_teleport=None,
                         collision_action=None, extra_args=("--end", "5"), subscribe=False)
    opts = dict(zip(*[iter(SumoSession(cfg, config=bare).command()[1:])] * 2))
    assert opts["--time-to-teleport"] == "30" and opts["--end"] == "5"  # config's, then ours
    assert "--seed" not in opts and opts["--no-step-log"] == "true"
