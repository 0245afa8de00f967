"""Scenes with nothing usable are refused with the reason; special files; message fixes."""

from __future__ import annotations

import dataclasses
import os
import socket
import subprocess
import sys
import tempfile

import numpy as np
import pytest

from conftest import ROOT, WOMD_DIR
from converters import iter_scene_records
from converters.scene_files import detect_format
from converters.tfrecord import encode_record
from converters.womd import scene_to_proto
from magail_sumo.errors import SceneFormatError
from magail_sumo.scene import SceneValidationError, Tracks, validate_scene


def _tracks(scene, **cols) -> Tracks:
    tr = scene.tracks
    fields = {f.name: getattr(tr, f.name) for f in dataclasses.fields(tr)}
    fields.update(cols)
    return Tracks(**fields)


def _refused(scene, match: str) -> str:
    with pytest.raises(SceneValidationError) as err:
        validate_scene(scene)
    assert match in str(err.value), str(err.value)
    return str(err.value)


def test_huge_but_finite_coordinates_are_out_of_range(scene_637f):
    tr = scene_637f.tracks
    x = np.full(tr.x.shape, 1e308)
    y = np.full(tr.y.shape, -1e308)
    text = _refused(dataclasses.replace(scene_637f, tracks=_tracks(scene_637f, x=x, y=y)),
                    "field x is 1e+308, out of range (|x| > 1e+07 m)")
    assert "non-finite" not in text and "not finite" not in text
    x = np.array(tr.x)
    x[3, 5] = np.inf
    _refused(dataclasses.replace(scene_637f, tracks=_tracks(scene_637f, x=x)),
             f"track {int(tr.id[3])} step 5: field x is inf, not finite")


@pytest.mark.parametrize("kind", ["zero", "reversed", "repeated"])
def test_timestamps_must_increase(scene_637f, kind):
    ts = np.array(scene_637f.timestamps)
    if kind == "zero":
        ts[:] = 0.0
    elif kind == "reversed":
        ts = ts[::-1].copy()
    else:
        ts[40] = ts[39]
    _refused(dataclasses.replace(scene_637f, timestamps=ts),
             "timestamps not strictly increasing: step ")


def test_zero_steps_and_no_valid_state_are_refused(scene_637f):
    cols = {f.name: getattr(scene_637f.tracks, f.name)[:, :0] for f in dataclasses.fields(Tracks)
            if f.name not in ("id", "type")}
    empty = dataclasses.replace(scene_637f, timestamps=np.zeros(0),
                                tracks=_tracks(scene_637f, **cols))
    _refused(empty, "scene has zero time steps")
    invalid = np.zeros(scene_637f.tracks.valid.shape, bool)
    _refused(dataclasses.replace(scene_637f, tracks=_tracks(scene_637f, valid=invalid)),
             "no track has a valid state")


@pytest.mark.parametrize("name, value, rule", [("length", 0.0, "positive"),
                                               ("width", -1.0, "positive"),
                                               ("height", -0.5, "non-negative")])
def test_box_sizes_on_valid_states(scene_637f, name, value, rule):
    tr = scene_637f.tracks
    i, t = (int(v[0]) for v in np.nonzero(tr.valid))
    arr = np.array(getattr(tr, name))
    arr[i, t] = value
    _refused(dataclasses.replace(scene_637f, tracks=_tracks(scene_637f, **{name: arr})),
             f"track {int(tr.id[i])} step {t}: box {name} {value:g} on a valid state "
             f"(must be {rule})")
    # the same value on an invalid state carries no meaning and is kept
    j, s = (int(v[0]) for v in np.nonzero(~tr.valid))
    arr = np.array(getattr(tr, name))
    arr[j, s] = value
    validate_scene(dataclasses.replace(scene_637f, tracks=_tracks(scene_637f, **{name: arr})))


def test_unusable_womd_record_is_a_one_line_error_with_the_reason(tmp_path, scene_637f):
    msg = scene_to_proto(scene_637f)
    for track in msg.tracks:
        for s in track.states:
            s.center_x, s.center_y = 1e308, -1e308
    path = tmp_path / "far.tfrecord"
    path.write_bytes(encode_record(msg.SerializeToString()))
    [rec] = list(iter_scene_records(path))
    assert "field x is 1e+308, out of range" in str(rec.error)


def test_real_scenes_still_valid(real_scene):
    validate_scene(real_scene)


def test_boundary_message_spelling(scene_637f):
    lane = next(ln for ln in scene_637f.roadmap.lanes if ln.right_boundaries)
    seg = dataclasses.replace(lane.right_boundaries[0], boundary_feature_id=987654321)
    bad = dataclasses.replace(lane, right_boundaries=(seg,) + lane.right_boundaries[1:])
    lanes = tuple(bad if ln is lane else ln for ln in scene_637f.roadmap.lanes)
    text = _refused(dataclasses.replace(scene_637f, roadmap=dataclasses.replace(
        scene_637f.roadmap, lanes=lanes)), f"lane {lane.id}: right_boundary feature 987654321")
    assert "boundariy" not in text


# ------------------------------------------------------------------ special files

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


# ------------------------------------------------------------------ realism submission messages

CONSTVEL = ROOT / "data" / "wosac" / "constvel_637f20cafde22ff8.binproto"


def _submission_error(tmp_path, edit) -> str:
    from converters.womd.protos import sim_agents_submission_pb2 as pb
    from magail_sumo.evaluation import iter_submission, read_submission
    from magail_sumo.evaluation.submission import rollouts_to_proto

    (good,) = read_submission(CONSTVEL)
    msg = rollouts_to_proto(good)
    edit(msg)
    path = tmp_path / "sub.binproto"
    path.write_bytes(pb.SimAgentsChallengeSubmission(scenario_rollouts=[msg]).SerializeToString())
    [rec] = list(iter_submission(path))
    return str(rec.error)


@pytest.mark.parametrize("field", ["center_x", "center_y", "heading"])
@pytest.mark.parametrize("rollout, agent", [(0, 0), (5, 2)])
def test_short_trajectory_field_is_named(tmp_path, field, rollout, agent):
    def edit(msg):
        del getattr(msg.joint_scenes[rollout].simulated_trajectories[agent], field)[-1]
    text = _submission_error(tmp_path, edit)
    assert text.endswith(f"79 steps of {field}, expected 80"), text


def test_huge_finite_coordinate_is_out_of_range_not_non_finite(scene_637f):
    from magail_sumo.evaluation import SubmissionError, read_submission, validate_rollouts

    (good,) = read_submission(CONSTVEL)
    x = np.array(good.x, np.float64)
    x[3, 1, 7] = 1e308
    ro = dataclasses.replace(good, x=x)
    with pytest.raises(SubmissionError) as err:
        validate_rollouts(ro, scene_637f)
    text = str(err.value)
    assert (f"rollout 3 agent {int(good.object_id[1])}: x 1e+308 out of range (|x| > 1e+07 m) "
            "at simulated step 7") in text, text
    assert "non-finite" not in text
