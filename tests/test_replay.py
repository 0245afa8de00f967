"""``magail-sumo replay``: a real scene through the env, written as GIF and MP4."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from conftest import ROOT, WOMD_DIR
from magail_sumo.cli.main import main


def _cli(*args):
    exe = shutil.which("magail-sumo")
    cmd = [exe] if exe else [sys.executable, "-m", "magail_sumo"]
    return subprocess.run([*cmd, *map(str, args)], capture_output=True, text=True, timeout=300,
                          cwd=ROOT)


@pytest.mark.sumo
def test_replay_gif_and_mp4(tmp_path):
    gif = tmp_path / "log.gif"
    out = _cli("replay", WOMD_DIR / "850c48d8bbfa008f.tfrecord", "--out", gif, "--size", "128")
    assert out.returncode == 0, out.stderr
    im = Image.open(gif)
    assert im.n_frames > 50 and im.size == (128, 128)
    im.seek(20)
    frame = np.asarray(im.convert("RGB"))
    assert (frame.reshape(-1, 3).std(axis=0) > 5).all()  # a map and boxes, not a blank frame
    mp4 = tmp_path / "random.mp4"
    out = _cli("replay", WOMD_DIR / "850c48d8bbfa008f.tfrecord", "--out", mp4, "--policy", "random",
               "--size", "128")
    assert out.returncode == 0, out.stderr
    assert mp4.stat().st_size > 1000 and mp4.read_bytes()[4:8] == b"ftyp"


def test_replay_refuses_unknown_format(tmp_path):
    out = _cli("replay", WOMD_DIR / "850c48d8bbfa008f.tfrecord", "--out", tmp_path / "x.avi")
    assert out.returncode != 0 and "x.avi: unsupported video format" in out.stderr


# ------------------------------------------------------------------------------------ bad arguments
SCENE = WOMD_DIR / "850c48d8bbfa008f.tfrecord"


@pytest.mark.parametrize("args, message", [
    (["--fps", "0"], "argument --fps: 0 is outside 1..100"),
    (["--fps", "-3"], "argument --fps: -3 is outside 1..100"),
    (["--size", "0"], "argument --size: 0 is outside 64..4096"),
    (["--size", "100000"], "argument --size: 100000 is outside 64..4096"),
    (["--fps", "ten"], "argument --fps: 'ten' is not an int"),
])
def test_replay_refuses_bad_numbers(tmp_path, capsys, args, message):
    with pytest.raises(SystemExit) as exc:
        main(["replay", str(SCENE), "--out", str(tmp_path / "v.gif"), *args])
    assert exc.value.code == 2
    assert capsys.readouterr().err.rstrip().endswith(message)


def test_replay_refuses_an_unwritable_out_before_the_slow_work(tmp_path, capsys, monkeypatch):
    from magail_sumo.cli import replay

    def slow_work(*args, **kwargs):  # the scene is read first of the slow work
        raise AssertionError("replay started its slow work")

    monkeypatch.setattr(replay, "load_scene", slow_work)
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["replay", str(SCENE), "--out", str(blocker / "v.gif")]) == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("error: magail-sumo replay: ")
    assert f"{blocker / 'v.gif'}: cannot be written ({blocker} is not a folder)" in err[0]
    assert main(["replay", str(SCENE), "--out", "/proc/no/v.gif"]) == 1
    assert "/proc/no/v.gif: cannot be written (" in capsys.readouterr().err
    (tmp_path / "d.gif").mkdir()
    assert main(["replay", str(SCENE), "--out", str(tmp_path / "d.gif")]) == 1
    assert "d.gif: is a folder" in capsys.readouterr().err


def test_replay_refuses_an_fcd_folder_before_the_slow_work(tmp_path, capsys, monkeypatch):
    """``--fcd DIR`` with an existing folder: one line asking for a file name; nothing is
    written beside the folder (no DIR.fcd.xml, DIR.types.add.xml, DIR.sumocfg)."""
    from magail_sumo.cli import replay

    def slow_work(*args, **kwargs):  # the scene is read first of the slow work
        raise AssertionError("replay started its slow work")

    monkeypatch.setattr(replay, "load_scene", slow_work)
    (tmp_path / "fcd").mkdir()
    assert main(["replay", str(SCENE), "--out", str(tmp_path / "v.gif"), "--fcd",
                 str(tmp_path / "fcd")]) == 1
    err = capsys.readouterr().err.splitlines()
    assert err == [f"error: magail-sumo replay: {tmp_path / 'fcd'}: is a folder (give a file "
                   "name like run.fcd.xml)"], err
    (tmp_path / "x.sumocfg").mkdir()  # a file beside the FCD that could not be written
    assert main(["replay", str(SCENE), "--out", str(tmp_path / "v.gif"), "--fcd",
                 str(tmp_path / "x.fcd.xml")]) == 1
    assert f"{tmp_path / 'x.sumocfg'}: is a folder" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == ["fcd", "x.sumocfg"]


@pytest.mark.sumo
def test_replay_a_policy_in_a_city_as_fcd(tmp_path, capsys):
    """A city (its folder) driven by a policy for N steps, recorded as FCD with the config that
    replays it in sumo-gui; a city without --fcd, or a recorded scene with a policy other than
    log / random, is one line."""
    from magail_sumo.cli.main import main as cli

    city = ROOT / "data" / "sumo" / "cologne8"
    fcd = tmp_path / "city.fcd.xml"
    assert cli(["replay", str(city), "--policy", "random", "--steps", "30",
                "--city-warmup-s", "30", "--fcd", str(fcd)]) == 0
    err = capsys.readouterr().err
    assert "cologne8: random drove 30 steps" in err and "sumo-gui -c" in err
    assert fcd.is_file() and (tmp_path / "city.sumocfg").is_file()
    assert "<timestep" in fcd.read_text()
    assert cli(["replay", str(city), "--policy", "random"]) == 1
    assert "a city is watched in sumo-gui: give --fcd" in capsys.readouterr().err
    scene = ROOT / "data" / "womd" / "637f20cafde22ff8.tfrecord"
    assert cli(["replay", str(scene), "--policy", "pretrained", "--out",
                str(tmp_path / "x.gif")]) == 1
    assert "a recorded scene replays with log or random" in capsys.readouterr().err
