"""``magail-sumo replay``: a real scene through the env, written as GIF and MP4."""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from conftest import ROOT, WOMD_DIR


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
