"""The command line: ``magail-sumo inspect`` end to end (the installed console script on real
and bad files, ``--skip-bad``), the top-level handler's one-line errors (``--debug`` for the
traceback), argument checks shared by the commands."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pytest

from conftest import EXPECTED, WOMD_DIR
from converters.tfrecord import encode_record, iter_records
from magail_sumo.cli.main import main


def run_cli(*args: str) -> subprocess.CompletedProcess:
    exe = shutil.which("magail-sumo")
    cmd = [exe] if exe else [sys.executable, "-m", "magail_sumo"]
    return subprocess.run([*cmd, *map(str, args)], capture_output=True, text=True, timeout=120)


def test_json_counts_for_every_real_scene():
    files = sorted(WOMD_DIR.glob("*.tfrecord"))
    out = run_cli("inspect", "--json", *files)
    assert out.returncode == 0, out.stderr
    records = [json.loads(line) for line in out.stdout.splitlines()]
    sanity = {r["scenario_id"]: r.pop("signal_sanity") for r in records}
    assert {r["scenario_id"]: r for r in records} == EXPECTED
    s = sanity["637f20cafde22ff8"]
    assert (s["signal_lanes"], s["records"]) == (12, 1092)
    assert s["red_light_runs"]["events"] == 0 and s["gaps"]["steps"] == 0
    assert s["unknown"] == {"steps": 540, "lanes": 12, "longest": 91}
    assert sanity["850c48d8bbfa008f"]["signal_lanes"] == 0


def test_text_output(tmp_path):
    out = run_cli("inspect", WOMD_DIR / "637f20cafde22ff8.tfrecord")
    assert out.returncode == 0
    assert "637f20cafde22ff8" in out.stdout and "4596" in out.stdout
    assert "70 vehicle, 10 pedestrian, 3 cyclist" in out.stdout
    assert "signal sanity     12 lanes; red-light runs 0 (0 vehicles); gaps 0 steps" in out.stdout


def _bad_files(tmp_path):
    good = next(iter(iter_records(WOMD_DIR / "850c48d8bbfa008f.tfrecord")))[1]
    files = {}
    rec = bytearray(encode_record(good))
    files["truncated"] = tmp_path / "truncated.tfrecord"
    files["truncated"].write_bytes(bytes(rec[:-100]))
    lc = bytearray(rec)
    lc[9] ^= 0xFF
    files["length CRC mismatch"] = tmp_path / "lencrc.tfrecord"
    files["length CRC mismatch"].write_bytes(bytes(lc))
    dc = bytearray(rec)
    dc[1000] ^= 0xFF
    files["data CRC mismatch"] = tmp_path / "datacrc.tfrecord"
    files["data CRC mismatch"].write_bytes(bytes(dc))
    files["not a TFRecord file"] = tmp_path / "text.tfrecord"
    files["not a TFRecord file"].write_text("hello world, certainly not a tfrecord")
    files["empty file"] = tmp_path / "empty.tfrecord"
    files["empty file"].write_bytes(b"")
    files["is a directory"] = tmp_path / "adir"
    files["is a directory"].mkdir()
    files["refused to load"] = tmp_path / "evil.pkl"
    files["refused to load"].write_bytes(
        b"cos\nsystem\n(S'echo pwned'\ntR.")  # protocol-0 pickle calling os.system
    return files


def test_each_bad_input_gives_one_line_error_and_nonzero_exit(tmp_path):
    for problem, path in _bad_files(tmp_path).items():
        out = run_cli("inspect", path)
        assert out.returncode != 0, problem
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1, (problem, out.stderr)
        assert str(path) in lines[0] and problem in lines[0], (problem, lines[0])
        assert "pwned" not in out.stdout


def test_skip_bad_reads_the_rest_and_counts(tmp_path):
    bad = _bad_files(tmp_path)
    files = [WOMD_DIR / "637f20cafde22ff8.tfrecord", *bad.values(), WOMD_DIR / "850c48d8bbfa008f.tfrecord"]
    out = run_cli("inspect", "--json", "--skip-bad", *files)
    assert out.returncode == 0, out.stderr
    ids = [json.loads(line)["scenario_id"] for line in out.stdout.splitlines()]
    assert ids == ["637f20cafde22ff8", "850c48d8bbfa008f"]
    summary = out.stderr.strip().splitlines()[-1]
    assert f"read 2 scene(s) from {len(files)} file(s); skipped {len(bad)}" in summary
    for problem in ("truncated record", "data CRC mismatch", "unsafe pickle", "empty file"):
        assert problem in summary


# ----------------------------------------------- the top-level handler, --skip-bad, argument checks
SID = "850c48d8bbfa008f"  # the smallest bundled scene
SCENE = WOMD_DIR / f"{SID}.tfrecord"


def test_unexpected_error_is_one_line_naming_command_and_input(monkeypatch, capsys):
    from magail_sumo.cli import inspect

    def boom(args):
        raise ValueError("something\nbroke")

    monkeypatch.setattr(inspect, "run", boom)
    assert main(["inspect", str(SCENE)]) == 1
    err = capsys.readouterr().err.splitlines()
    assert err[0] == f"error: magail-sumo inspect: {SCENE}: ValueError: something broke"
    assert err[1] == "(run with --debug for the traceback)" and len(err) == 2
    assert main(["--debug", "inspect", str(SCENE)]) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and err.rstrip().endswith("ValueError: something broke")
    assert main(["inspect", str(SCENE), "--debug"]) == 1
    assert "Traceback" in capsys.readouterr().err

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(inspect, "run", interrupted)
    assert main(["inspect", str(SCENE)]) == 130


def test_inspect_skip_bad_goes_on_past_a_failing_scene(monkeypatch, capsys):
    from magail_sumo.scene import Scene

    real = Scene.summary

    def summary(self):
        if self.scenario_id == SID:
            raise KeyError("lost")
        return real(self)

    monkeypatch.setattr(Scene, "summary", summary)
    other = WOMD_DIR / "2831b6fde0420b0d.tfrecord"
    assert main(["inspect", "--skip-bad", "--json", str(SCENE), str(other)]) == 0
    out, err = capsys.readouterr()
    assert '"2831b6fde0420b0d"' in out
    assert f"scene {SID}: KeyError: 'lost'" in err
    assert main(["inspect", str(SCENE), str(other)]) == 1


def test_timeout_flag_is_checked(capsys):
    for cmd in (["convert", str(SCENE), "--out", "x"],
                ["evaluate", "--policy", "constvel", "--scenes", str(SCENE), "--out", "x"],
                ["expert", str(SCENE), "--out", "x"]):
        with pytest.raises(SystemExit):
            main([*cmd, "--timeout-s", "0"])
        assert "argument --timeout-s: 0 is outside" in capsys.readouterr().err


def test_phase_bars_draw_on_a_terminal_only_and_restart_a_phase(capsys):
    from magail_sumo.cli.progress import PhaseBars

    quiet = PhaseBars(enabled=False)
    quiet("rollouts", 1, 4)
    assert capsys.readouterr().err == ""
    bars = PhaseBars(enabled=True)
    seen = []
    for update in range(2):
        for k in range(1, 4):
            bars("steps", k, 3)  # counts anew each update: a new bar, never a negative step
        seen.append((bars.bars["steps"], bars.bars["steps"].n))
    bars("rollouts", 2, 8)
    bars("rollouts", 8, 8)
    assert seen[0][0] is not seen[1][0] and seen[0][1] == seen[1][1] == 3
    assert bars.bars["rollouts"].n == 8
    bars.close()
    err = capsys.readouterr().err
    assert "env steps of the update" in err and "rollouts" in err
