"""Scene files that are no regular file (a FIFO, a character device, a socket, a symlink loop, a
dangling link, a missing file) are refused with the reason, without blocking, and
``--skip-bad`` goes on past them (``converters.scene_files``)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile

import pytest

from conftest import ROOT, WOMD_DIR
from converters import iter_scene_records
from converters.scene_files import detect_format
from magail_sumo.errors import SceneFormatError


def _inspect(*paths) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "magail_sumo.cli.main", "inspect", *map(str, paths)],
                          capture_output=True, text=True, timeout=60, cwd=ROOT)


def test_fifo_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "scene.tfrecord"
    os.mkfifo(fifo)
    out = _inspect(fifo)  # would block forever (and time out) if the FIFO were opened
    assert out.returncode == 1
    assert out.stderr.strip() == f"error: {fifo}: is a FIFO (named pipe), expected a regular file"
    pkl = tmp_path / "scene.pkl"
    os.mkfifo(pkl)
    with pytest.raises(SceneFormatError, match="is a FIFO"):
        detect_format(pkl)


def test_skip_bad_goes_on_after_special_files(tmp_path):
    fifo = tmp_path / "p.tfrecord"
    os.mkfifo(fifo)
    loop_a, loop_b = tmp_path / "a.tfrecord", tmp_path / "b.tfrecord"
    os.symlink(loop_b, loop_a)
    os.symlink(loop_a, loop_b)
    out = _inspect("--skip-bad", fifo, loop_a, WOMD_DIR / "850c48d8bbfa008f.tfrecord")
    assert out.returncode == 0, out.stderr
    assert "850c48d8bbfa008f" in out.stdout
    assert f"{loop_a}: symlink loop (too many levels of symbolic links)" in out.stderr


def test_symlink_loop_device_socket_and_dangling_link(tmp_path):
    a, b = tmp_path / "a.pkl", tmp_path / "b.pkl"
    os.symlink(b, a)
    os.symlink(a, b)
    with pytest.raises(SceneFormatError, match=r"a\.pkl: symlink loop"):
        detect_format(a)
    dangling = tmp_path / "d.tfrecord"
    os.symlink(tmp_path / "nowhere", dangling)
    with pytest.raises(SceneFormatError, match="broken symbolic link"):
        detect_format(dangling)
    with pytest.raises(SceneFormatError, match="no such file"):
        detect_format(tmp_path / "missing.tfrecord")
    if os.path.exists("/dev/null"):
        [rec] = list(iter_scene_records("/dev/null"))
        assert str(rec.error) == "/dev/null: is a character device, expected a regular file"
    with tempfile.TemporaryDirectory(dir="/tmp") as short:  # AF_UNIX paths are short
        path = os.path.join(short, "s.tfrecord")
        with socket.socket(socket.AF_UNIX) as sock:
            sock.bind(path)
            [rec] = list(iter_scene_records(path))
            assert str(rec.error) == f"{path}: is a socket, expected a regular file"
