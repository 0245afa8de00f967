"""Outputs (``magail_sumo.outputs``): paths derived from data, output-folder ownership, atomic
writes (issue 16).

Scene ids are data: an absolute id, ``..``, ``/``, an empty id, ``.``, NUL, a newline or 5,000
characters must neither write outside the output folder nor end a batch with a traceback. One
real pipeline (convert -> expert -> evaluate -> report, laid out as the README demo) runs over a
TFRecord holding the smallest bundled scene under every hostile id; the other tests are cheap
(no SUMO run, or netconvert only). Full disks are simulated by making the write of the target
file raise ``ENOSPC`` half-way (SUMO itself is never mocked).
"""

from __future__ import annotations

import csv
import dataclasses
import errno
import io
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from conftest import ROOT, WOMD_DIR, tree_digest
from converters import load_scene
from converters.womd import write_womd
from magail_sumo.cli.main import main
from magail_sumo.outputs import MARKER, OutputError, read_marker, safe_name

SID = "850c48d8bbfa008f"


def _hostile_ids(canary: Path) -> list[str]:
    return [str(canary / "abs"),  # absolute: would land in the canary folder
            "../../esc", "..", "a/b", "", ".", "nul\x00id", "new\nline", "L" * 5000]


def _changed_outside(before: dict[str, str], after: dict[str, str], allowed: list[str]
                     ) -> list[str]:
    """Paths added or changed in ``after`` that are not under one of ``allowed``."""
    return sorted(p for p, h in after.items() if before.get(p) != h
                  and not any(p == a or p.startswith(a + os.sep) for a in allowed))


def _one_line_errors(err: str) -> None:
    """Every stderr line is an error line or a summary line: no traceback, no split line."""
    for line in err.splitlines():
        assert line.startswith(("error:", "converted ", "evaluated ", "recorded ", "report:")), line
    assert "Traceback" not in err


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """tmp/{canary/, inputs/hostile.tfrecord}: the canary holds one file that must never
    change; the TFRecord holds scene 850c under every hostile id."""
    root = tmp_path_factory.mktemp("hostile")
    canary = root / "canary"
    canary.mkdir()
    (canary / "keep.txt").write_text("do not touch\n")
    base = load_scene(WOMD_DIR / f"{SID}.tfrecord")
    ids = _hostile_ids(canary)
    (root / "inputs").mkdir()
    write_womd(root / "inputs" / "hostile.tfrecord",
               [dataclasses.replace(base, scenario_id=i) for i in ids])
    # expert starts a process per scene (~5 s each): a subset of the ids
    write_womd(root / "inputs" / "expert.tfrecord",
               [dataclasses.replace(base, scenario_id=i) for i in _expert_ids(ids)])
    return root, ids


def _expert_ids(ids: list[str]) -> list[str]:
    """Absolute, .., empty, newline and long ids."""
    return [ids[0], "../../esc", "", "new\nline", "L" * 5000]


def test_safe_names_are_files_and_real_ids_unchanged(world):
    _, ids = world
    for f in WOMD_DIR.glob("*.tfrecord"):
        assert safe_name(f.stem) == f.stem
    names = [safe_name(i) for i in ids]
    assert len(set(names)) == len(ids)
    for n in names:
        assert "/" not in n and "\x00" not in n and not n.startswith(".") and len(n) <= 100


@pytest.mark.sumo
def test_pipeline_with_hostile_ids_stays_inside(world, capsys, monkeypatch):
    """README layout (convert --out out, expert --networks out --out out/expert, evaluate
    --networks out --out out/eval, report out/eval) over every hostile id: every file lands
    under out/, named by safe_name, with the original ids in the metadata."""
    root, ids = world
    work = root / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    out = work / "out"
    src = str(root / "inputs" / "hostile.tfrecord")
    before = tree_digest(root)

    assert main(["convert", src, "--out", str(out), "--no-baseline"]) == 0
    err = capsys.readouterr().err
    _one_line_errors(err)
    for sid in ids:
        folder = out / safe_name(sid)
        assert json.loads((folder / "conversion.json").read_text())["scenario_id"] == sid
        assert (folder / f"{safe_name(sid)}.net.xml").is_file()
    rows = list(csv.DictReader(open(out / "summary.csv", newline="")))
    assert [r["scenario_id"] for r in rows] == ids and {r["status"] for r in rows} == {"ok"}
    assert "convert" in read_marker(out)["tools"]

    assert main(["expert", str(root / "inputs" / "expert.tfrecord"), "--networks", str(out),
                 "--out", str(out / "expert"), "--workers", "2"]) == 0
    meta = json.loads((out / "expert" / "metadata.json").read_text())
    assert [s["scenario_id"] for s in meta["scenes"]] == _expert_ids(ids)
    for sc in meta["scenes"]:
        assert sc["parquet"] == f"{safe_name(sc['scenario_id'])}.parquet"
        table = pd.read_parquet(out / "expert" / sc["parquet"], columns=["scene_id"])
        assert set(table["scene_id"]) == {sc["scenario_id"]}

    assert main(["evaluate", "--policy", "constvel", "--baselines", "sumo", "--scenes", src,
                 "--rollouts", "1", "--networks", str(out), "--out", str(out / "eval"),
                 "--workers", "2"]) == 0
    _one_line_errors(capsys.readouterr().err)
    man = json.loads((out / "eval" / "manifest.json").read_text())
    assert [s["scenario_id"] for s in man["scenes"]] == ids
    assert not (out / "eval" / "networks").exists()  # the bundles of out/ were found
    for sid in ids:
        for m in ("constvel", "sumo"):
            df = pd.read_parquet(out / "eval" / "rollouts" / m / f"{safe_name(sid)}.parquet",
                                 columns=["scenario_id"])
            assert set(df["scenario_id"].astype(str)) == {sid}

    assert main(["report", str(out / "eval")]) == 0
    _one_line_errors(capsys.readouterr().err)
    assert (out / "eval" / "report" / "report.html").is_file()
    assert not list((out / "eval" / "report" / "img").glob("*/*"))  # image names are names

    after = tree_digest(root)
    assert _changed_outside(before, after, [os.path.join("work", "out")]) == []
    assert (root / "canary" / "keep.txt").read_text() == "do not touch\n"
    assert sorted(os.listdir(root / "canary")) == ["keep.txt"]
    assert not [p for p in after if p.endswith((".tmp", ".old"))]  # no temporaries left


@pytest.mark.sumo
def test_replay_with_hostile_id(tmp_path):
    one = tmp_path / "one.tfrecord"
    write_womd(one, [dataclasses.replace(load_scene(WOMD_DIR / f"{SID}.tfrecord"),
                                         scenario_id="../../new\nline")])
    before = tree_digest(tmp_path)
    gif = tmp_path / "vid" / "r.gif"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    r = subprocess.run([sys.executable, "-m", "magail_sumo", "replay", str(one), "--out",
                        str(gif), "--size", "64"], capture_output=True, text=True, timeout=300,
                       cwd=tmp_path, env=env)  # a process of its own: libsumo runs in it
    assert r.returncode == 0, r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("../../new\\nline: ")
    assert gif.stat().st_size > 0
    assert _changed_outside(before, tree_digest(tmp_path), ["vid"]) == []
    assert sorted(os.listdir(gif.parent)) == ["r.gif"]


@pytest.mark.sumo
def test_name_collision_is_an_error_not_an_overwrite(tmp_path, capsys):
    base = load_scene(WOMD_DIR / f"{SID}.tfrecord")
    twin = safe_name("a/b")  # a plain id equal to the safe name of another id
    src = tmp_path / "twins.tfrecord"
    write_womd(src, [dataclasses.replace(base, scenario_id="a/b"),
                     dataclasses.replace(base, scenario_id=twin)])
    out = tmp_path / "out"
    assert main(["convert", str(src), "--out", str(out), "--no-baseline", "--skip-bad"]) == 0
    err = capsys.readouterr().err
    _one_line_errors(err)
    assert "map to the same file name" in err
    assert json.loads((out / twin / "conversion.json").read_text())["scenario_id"] == "a/b"
    rows = list(csv.DictReader(open(out / "summary.csv", newline="")))
    assert [r["status"] for r in rows] == ["ok", "failed"]
    # expert reports the second scene of the pair (one line) and records only the first
    assert main(["expert", str(src), "--networks", str(out), "--out", str(tmp_path / "ex")]) == 1
    err = capsys.readouterr().err
    _one_line_errors(err)
    lines = err.strip().splitlines()
    assert len(lines) == 2 and "map to the same file name" in lines[0]
    meta = json.loads((tmp_path / "ex" / "metadata.json").read_text())
    assert [s["scenario_id"] for s in meta["scenes"]] == ["a/b"]
    assert sorted(p.name for p in (tmp_path / "ex").glob("*.parquet")) == [f"{twin}.parquet"]


@pytest.mark.sumo
def test_error_lines_with_hostile_ids_stay_one_line(world, tmp_path, capsys):
    """Errors naming a hostile id (newline, NUL, 5,000 characters) are one escaped line each."""
    root, ids = world
    src = str(root / "inputs" / "hostile.tfrecord")
    out = tmp_path / "eval"
    assert main(["evaluate", "--policy", "constvel", "--baselines", "none", "--rollouts", "1",
                 "--scenes", src, src, "--out", str(out)]) == 1
    err = capsys.readouterr().err
    _one_line_errors(err)
    assert err.count("given twice") == len(ids)
    assert "scenario new\\nline: given twice" in err and "nul\\x00id" in err
    assert max(len(line) for line in err.splitlines()) < 1000
    from converters.sumo.scenario import claim_networks_dir

    conv = claim_networks_dir(tmp_path / "conv")  # ours, but a folder of someone in the way
    (conv / safe_name("new\nline")).mkdir()
    (conv / safe_name("new\nline") / "notes.txt").write_text("mine")
    assert main(["convert", src, "--out", str(conv), "--no-baseline", "--skip-bad"]) == 0
    err = capsys.readouterr().err
    _one_line_errors(err)
    assert "error: new\\nline: output: " in err and "not a converted bundle" in err
    assert sorted(os.listdir(conv / safe_name("new\nline"))) == ["notes.txt"]


def test_conversion_refuses_to_replace_a_foreign_folder(tmp_path):
    from converters.sumo import convert_scene

    scene = load_scene(WOMD_DIR / f"{SID}.tfrecord")
    (tmp_path / SID).mkdir()
    (tmp_path / SID / "notes.txt").write_text("mine")
    rep = convert_scene(scene, tmp_path)
    assert rep.status == "failed" and "not a converted bundle" in rep.reason
    assert sorted(os.listdir(tmp_path / SID)) == ["notes.txt"]
    assert sorted(os.listdir(tmp_path)) == [SID]


# ----------------------------------------------------------------------------------- ownership
@pytest.mark.parametrize("cmd,name", [
    (["evaluate", "--policy", "constvel", "--baselines", "none", "--rollouts", "1",
      "--scenes", str(WOMD_DIR / f"{SID}.tfrecord"), "--out", "{d}"], "manifest.json"),
    (["expert", str(WOMD_DIR / f"{SID}.tfrecord"), "--networks", str(ROOT / "networks"),
      "--out", "{d}"], "metadata.json"),
    (["convert", str(WOMD_DIR / f"{SID}.tfrecord"), "--no-baseline", "--out", "{d}"],
     "summary.csv"),
    (["report", str(WOMD_DIR), "--out", "{d}"], "report.html"),
])
def test_foreign_folder_is_refused(tmp_path, capsys, cmd, name):
    d = tmp_path / "theirs"
    d.mkdir()
    (d / name).write_text("someone else's file\n")
    before = tree_digest(tmp_path)
    assert main([a.replace("{d}", str(d)) for a in cmd]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not empty and was not written by magail_sumo" in err
    assert tree_digest(tmp_path) == before


def test_reruns_into_own_folders_are_accepted(tmp_path, capsys):
    """A folder a command marked is its own on the next run (manifest merged, report redone)."""
    src = str(WOMD_DIR / f"{SID}.tfrecord")
    out = tmp_path / "eval"
    for method in ("constvel", "logreplay"):
        assert main(["evaluate", "--policy", method, "--baselines", "none", "--rollouts", "1",
                     "--scenes", src, "--out", str(out)]) == 0
    assert json.loads((out / "manifest.json").read_text())["methods"] == ["constvel",
                                                                         "logreplay"]
    for _ in range(2):
        assert main(["report", str(out)]) == 0
    assert set(read_marker(out)["tools"]) == {"evaluate"}
    assert set(read_marker(out / "report")["tools"]) == {"report"}
    _one_line_errors(capsys.readouterr().err)


def test_networks_folders(tmp_path):
    from converters.sumo.scenario import claim_networks_dir

    shipped = tmp_path / "networks"  # as a fresh clone has it: README + bundles, no marker
    shutil.copytree(ROOT / "networks", shipped, ignore=shutil.ignore_patterns(MARKER))
    claim_networks_dir(shipped)
    assert "convert" in read_marker(shipped)["tools"]
    other = tmp_path / "photos"
    other.mkdir()
    (other / "a.jpg").write_bytes(b"x")
    with pytest.raises(OutputError, match="not written by magail_sumo"):
        claim_networks_dir(other)
    assert sorted(os.listdir(other)) == ["a.jpg"]
    readme = tmp_path / "project"  # a README (or a summary.csv) alone is not a networks folder
    readme.mkdir()
    (readme / "README.md").write_text("x")
    with pytest.raises(OutputError, match="not written by magail_sumo"):
        claim_networks_dir(readme)


# ---------------------------------------------------------------------------------- full disk
def _full_disk(monkeypatch, needle: str) -> None:
    """Opening a file for writing whose path contains ``needle`` gives a file whose first write
    stores half its data and raises ENOSPC (plain ``open``, ``Path.write_text`` and the
    ``os.fdopen`` of atomic writes)."""

    class Full:
        def __init__(self, fh):
            self._fh = fh

        def write(self, data):
            self._fh.write(data[:max(1, len(data) // 2)])
            self._fh.flush()
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        def __getattr__(self, name):
            return getattr(self._fh, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self._fh.close()

    real_open, real_fdopen = io.open, os.fdopen

    def fake_open(file, mode="r", *a, **k):
        fh = real_open(file, mode, *a, **k)
        return Full(fh) if any(c in mode for c in "wax") and needle in str(file) else fh

    def fake_fdopen(fd, mode="r", *a, **k):
        path = os.readlink(f"/proc/self/fd/{fd}")
        fh = real_fdopen(fd, mode, *a, **k)
        return Full(fh) if needle in path else fh

    monkeypatch.setattr(io, "open", fake_open)
    monkeypatch.setattr("builtins.open", fake_open)
    monkeypatch.setattr(os, "fdopen", fake_fdopen)


def _partial_files(folder: Path) -> list[str]:
    return sorted(p for p in tree_digest(folder) if p.endswith((".tmp", ".old")) or "/." in p
                  or p.startswith("."))


@pytest.mark.sumo
@pytest.mark.parametrize("needle", [".rou.xml", "conversion.json"])
def test_full_disk_during_convert_leaves_old_bundle_or_none(tmp_path, capsys, monkeypatch,
                                                           needle):
    src = str(WOMD_DIR / f"{SID}.tfrecord")
    fresh, again = tmp_path / "fresh", tmp_path / "again"
    assert main(["convert", src, "--out", str(again), "--no-baseline"]) == 0
    old = tree_digest(again / SID)
    capsys.readouterr()
    _full_disk(monkeypatch, needle)
    for out in (fresh, again):  # --force: reconvert the bundle convert would skip as done
        assert main(["convert", src, "--out", str(out), "--no-baseline", "--force"]) == 1
        err = capsys.readouterr().err
        _one_line_errors(err)
        assert "No space left on device" in err
    monkeypatch.undo()
    assert not (fresh / SID).exists()  # no half-written bundle
    assert tree_digest(again / SID) == old  # the old bundle, untouched
    assert _partial_files(fresh) == [MARKER] and _partial_files(again) == [MARKER]


@pytest.mark.sumo
def test_full_disk_on_summary_and_manifest_keeps_old_files(tmp_path, capsys, monkeypatch):
    from magail_sumo.evaluation.report import _write_csv
    from magail_sumo.evaluation.report.render import Document
    from magail_sumo.evaluation.storage import write_manifest, write_parquet
    from magail_sumo.evaluation.submission import write_submission

    src = str(WOMD_DIR / f"{SID}.tfrecord")
    out = tmp_path / "out"
    assert main(["convert", src, "--out", str(out), "--no-baseline"]) == 0
    old_summary = (out / "summary.csv").read_bytes()
    capsys.readouterr()
    _full_disk(monkeypatch, "summary.csv")
    assert main(["convert", src, "--out", str(out), "--no-baseline"]) == 1
    err = capsys.readouterr().err
    _one_line_errors(err)
    assert "summary.csv: cannot write (No space left on device)" in err
    assert (out / "summary.csv").read_bytes() == old_summary
    monkeypatch.undo()

    # manifest, report files, submission: old content kept, no temporary left
    d = tmp_path / "files"
    d.mkdir()
    man = {"scenes": [], "methods": ["constvel"], "rollouts": 1, "seed": 0}
    write_manifest(d, man)
    for name in ("metrics.csv", "report.html", "sub.binproto"):
        (d / name).write_text("old\n")
    old = tree_digest(d)
    _full_disk(monkeypatch, str(d))
    with pytest.raises(OSError):
        write_manifest(d, {**man, "methods": ["sumo"]})
    with pytest.raises(OSError):
        _write_csv(d / "metrics.csv", ["a"], [[1]])
    with pytest.raises(OSError):
        Document("t", d / "img").write(d / "report.html", d / "report.md")
    with pytest.raises(OSError):
        write_submission(d / "sub.binproto", [])
    monkeypatch.undo()
    assert tree_digest(d) == old

    from magail_sumo.expert import record_expert

    ex = tmp_path / "expert"
    record_expert([], ex)
    old = tree_digest(ex)
    _full_disk(monkeypatch, "metadata.json")
    with pytest.raises(OSError):
        record_expert([], ex)
    monkeypatch.undo()
    assert tree_digest(ex) == old

    class HalfFrame:  # a Parquet writer that fills the disk half-way
        def to_parquet(self, path, index=False):
            Path(path).write_bytes(b"PAR1" + b"\0" * 100)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    target = d / "rollouts" / "constvel" / f"{SID}.parquet"
    with pytest.raises(OSError):
        write_parquet(target, HalfFrame())
    assert os.listdir(target.parent) == []


def test_full_disk_on_real_tmpfs(tmp_path, capsys):
    """Optional: a real 200 KiB tmpfs (needs root and mount); the 637f net alone is bigger."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=200k", "tmpfs", str(mnt)],
                       capture_output=True)
    if r.returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        out = mnt / "out"
        rc = main(["convert", str(WOMD_DIR / "637f20cafde22ff8.tfrecord"), "--out", str(out),
                   "--no-baseline"])
        err = capsys.readouterr().err
        assert rc == 1
        _one_line_errors(err)
        assert "No space left on device" in err  # netconvert itself does not notice
        assert not (out / "637f20cafde22ff8").exists()
        assert not [p for p in tree_digest(mnt) if p.endswith((".tmp", ".old"))]
    finally:
        subprocess.run(["umount", str(mnt)], capture_output=True)


# ---------------------------------------------------------- symbolic links out of the folder
def _outside(tmp_path: Path) -> Path:
    """tmp/outside/: a sibling of the output folder holding a file that must never change."""
    o = tmp_path / "outside"
    o.mkdir()
    (o / "precious.txt").write_text("precious\n")
    return o


def _refused(err: str, path: Path) -> str:
    """The one error line of ``err``: a refusal naming ``path`` (no traceback)."""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert f"{path}: would be written outside" in lines[0], err
    return lines[0]


def test_inside_follows_links_only_within_the_folder(tmp_path):
    from magail_sumo.outputs import inside, inside_dir

    out, outside = tmp_path / "out", _outside(tmp_path)
    out.mkdir()
    (out / "real").mkdir()
    (out / "in_link").symlink_to(out / "real")  # stays inside: accepted
    (out / "out_link").symlink_to(outside)
    (out / "dangling").symlink_to(outside / "new.txt")
    (out / "file").write_text("x")
    assert inside(out, "in_link", "a.txt") == out / "in_link" / "a.txt"
    assert inside_dir(out, "in_link", "sub") == out / "in_link" / "sub"
    assert (out / "real" / "sub").is_dir()
    for parts in (("out_link",), ("out_link", "a.txt"), ("dangling",), ("..", "x")):
        with pytest.raises(OutputError, match="would be written outside") as e:
            inside_dir(out, *parts)
        assert "\n" not in str(e.value) and str(out.joinpath(*parts)) in str(e.value)
    with pytest.raises(OutputError, match="file: exists and is not a folder"):
        inside_dir(out, "file")
    assert tree_digest(outside) == {"precious.txt": tree_digest(outside)["precious.txt"]}
    assert not (outside / "new.txt").exists()


def _planted(out: Path, name: str, outside: Path) -> Path:
    """``out/name``, made a symbolic link to ``outside`` (a folder) or, for a file name, to
    ``outside/precious.txt``."""
    link = out / name
    link.parent.mkdir(parents=True, exist_ok=True)
    link.symlink_to(outside if "." not in name else outside / "precious.txt")
    return link


def test_report_figures_refuse_a_link_out(tmp_path):
    """The report's figure writer (report/img, the Markdown's images)."""
    from magail_sumo.evaluation.report.render import Document

    out, outside = tmp_path / "report", _outside(tmp_path)
    link = _planted(out, "img", outside)
    before = tree_digest(outside)
    with pytest.raises(OutputError, match=f"{link}: would be written outside"):
        Document("t", out / "img").image(b"\x89PNG", "bars", "bars")
    assert tree_digest(outside) == before


@pytest.mark.parametrize("name", ["networks", "manifest.json"])
def test_evaluation_write_sites_refuse_links_out(tmp_path, name):
    """The bundles of evaluate (OUT/networks, handed to the converter; the outside folder a
    networks folder, so only the link stands in the way) and its manifest."""
    from converters.sumo.scenario import claim_networks_dir
    from magail_sumo.evaluation.scenes import bundle
    from magail_sumo.evaluation.storage import write_manifest

    out, outside = tmp_path / "eval", claim_networks_dir(tmp_path / "outside")
    (outside / "precious.txt").write_text("precious\n")
    link = _planted(out, name, outside)
    before = tree_digest(outside)
    with pytest.raises(OutputError, match=f"{link}: would be written outside"):
        if name == "networks":
            bundle(load_scene(WOMD_DIR / f"{SID}.tfrecord"), None, out)
        else:
            write_manifest(out, {"scenes": [], "methods": [], "rollouts": 1, "seed": 0})
    assert tree_digest(outside) == before


def test_expert_metadata_refuses_a_link_out(tmp_path):
    from magail_sumo.expert import record_expert

    out, outside = tmp_path / "expert", _outside(tmp_path)
    out.mkdir()
    (out / MARKER).write_text(json.dumps({"tools": {"expert": ["metadata.json"]}}))
    link = _planted(out, "metadata.json", outside)
    before = tree_digest(outside)
    with pytest.raises(OutputError, match=f"{link}: would be written outside"):
        record_expert([], out)
    assert tree_digest(outside) == before and os.path.islink(link)


@pytest.fixture(scope="module")
def eval_dir(tmp_path_factory):
    """An evaluate folder: constvel on scene 850c, one rollout (no SUMO run)."""
    out = tmp_path_factory.mktemp("linked") / "eval"
    assert main(["evaluate", "--policy", "constvel", "--baselines", "none", "--rollouts", "1",
                 "--scenes", str(WOMD_DIR / f"{SID}.tfrecord"), "--out", str(out)]) == 0
    return out


@pytest.mark.parametrize("name", ["report", "report/img", "report/report.html"])
def test_report_refuses_links_out_of_its_folder(eval_dir, tmp_path, capsys, name):
    """``report DIR`` with DIR/report, DIR/report/img or a report file a symbolic link out of
    DIR (the outside folder marked as a report's, so only the link stands in the way): refused
    in one line naming the link before any scoring; nothing outside changes."""
    d = tmp_path / "eval"
    shutil.copytree(eval_dir, d)
    outside = _outside(tmp_path)
    (outside / MARKER).write_text(json.dumps({"tools": {"report": ["report.html"]}}))
    (outside / "report.html").write_text("precious\n")
    (outside / "01_bars.png").write_text("precious\n")
    if name != "report":
        (d / "report").mkdir()
        (d / "report" / MARKER).write_text(json.dumps({"tools": {"report": []}}))
    link = _planted(d, name, outside)
    before = tree_digest(outside)
    capsys.readouterr()
    assert main(["report", str(d)]) == 1
    _refused(capsys.readouterr().err, link)
    assert tree_digest(outside) == before


@pytest.mark.sumo
def test_evaluate_refuses_a_networks_link_out_of_its_folder(tmp_path, capsys):
    """``evaluate --out OUT`` (OUT marked as evaluate's) whose OUT/networks is a symbolic link
    to a networks folder outside: refused before any conversion or rollout; nothing is
    converted into the outside folder."""
    from converters.sumo.scenario import claim_networks_dir

    out, outside = tmp_path / "eval", claim_networks_dir(tmp_path / "outside")
    (outside / "precious.txt").write_text("precious\n")
    out.mkdir()
    (out / MARKER).write_text(json.dumps({"tools": {"evaluate": ["networks"]}}))
    link = _planted(out, "networks", outside)
    before = tree_digest(outside)
    assert main(["evaluate", "--policy", "constvel", "--baselines", "none", "--rollouts", "1",
                 "--fcd-rollouts", "1", "--scenes", str(WOMD_DIR / f"{SID}.tfrecord"),
                 "--out", str(out)]) == 1
    _refused(capsys.readouterr().err, link)
    assert tree_digest(outside) == before
    assert sorted(os.listdir(out)) == [MARKER, "networks"]


# ------------------------------------------------------------------------- invalid markers
@pytest.mark.parametrize("content,why", [
    ("[" * 100000, "nested too deep"),
    ('{"tools": {"train": "abc"}}', "expected"),  # a string: its letters are not file names
    ('{"tools": {"train": [1, null]}}', "expected"),
    ('{"tools": ["train"]}', "expected"),
    ('"tools"', "expected"),
    ('{"tools": {', "not JSON"),
    (b"\xff\xfe{}", "not JSON"),
])
def test_invalid_marker_is_one_line_naming_it_and_nothing_is_removed(tmp_path, content, why):
    from magail_sumo.outputs import claim_output_dir, remove_owned

    d = tmp_path / "run"
    d.mkdir()
    for name in ("a", "b", "c", "train"):
        (d / name).write_text(name)
    marker = d / MARKER
    marker.write_bytes(content if isinstance(content, bytes) else content.encode())
    before = tree_digest(d)
    for call in (read_marker, lambda f: remove_owned(f, "train"),
                 lambda f: claim_output_dir(f, "train", ["a"])):
        with pytest.raises(OutputError) as e:
            call(d)
        msg = str(e.value)
        assert msg.startswith(f"{marker}: not a valid magail_sumo marker (") and why in msg
        assert "\n" not in msg and len(msg) < 400
    assert tree_digest(d) == before


def test_a_marker_that_is_a_fifo_is_refused_at_once(tmp_path):
    """``convert --out DIR`` whose marker is a FIFO hung on open(); now one line."""
    import time

    from magail_sumo.outputs import claim_output_dir

    d = tmp_path / "nets"
    d.mkdir()
    os.mkfifo(d / MARKER)
    t0 = time.monotonic()
    for call in (read_marker, lambda f: claim_output_dir(f, "convert")):
        with pytest.raises(OutputError, match=r"not a valid magail_sumo marker \(is a FIFO"):
            call(d)
    assert time.monotonic() - t0 < 5


# ------------------------------------------------------------------- atomic writes' errors
def test_failed_atomic_write_names_the_target_not_a_temporary_file(tmp_path):
    from magail_sumo.outputs import atomic_path, write_bytes

    (tmp_path / "d").mkdir()
    with pytest.raises(OutputError, match=r"d: is a folder \(give a file name\)"):
        write_bytes(tmp_path / "d", b"x")
    assert os.listdir(tmp_path) == ["d"] and os.listdir(tmp_path / "d") == []
    for target in (tmp_path / "no" / "f.bin", tmp_path / "d" / "f.bin"):
        with pytest.raises(OSError) as e:
            if target.parent.name == "no":
                write_bytes(target, b"x")
            else:
                with atomic_path(target) as tmp:  # a writer failing on its temporary file
                    os.mkdir(tmp)
        assert e.value.filename == str(target), e.value
    assert os.listdir(tmp_path / "d") == []
    with pytest.raises(OSError) as e:  # an error about another file (one read) is left as is
        with atomic_path(tmp_path / "d" / "f.bin"):
            open(tmp_path / "absent.txt")
    assert e.value.filename == str(tmp_path / "absent.txt")


def test_full_disk_names_the_file_being_written(tmp_path):
    """A real full disk (a 64 KiB tmpfs): the OSError names the target, ENOSPC."""
    from conftest import small_tmpfs
    from magail_sumo.outputs import write_bytes

    with small_tmpfs(tmp_path / "small", "64k") as mnt:
        with pytest.raises(OSError) as e:
            write_bytes(mnt / "big.bin", b"x" * (1 << 20))
        assert e.value.errno == errno.ENOSPC and e.value.filename == str(mnt / "big.bin")
        assert os.listdir(mnt) == []


def test_ids_that_look_like_the_tools_own_files_get_a_digest():
    """A scenario id named like a file or folder the tool writes beside the scenes' outputs
    (``summary.csv``, ``report``) is not used as is: it would take that file's place."""
    from magail_sumo.outputs import safe_name

    for sid in ("summary.csv", "SUMMARY.CSV", "manifest.json", "report", "city", "x.yaml"):
        name = safe_name(sid)
        assert name.startswith(f"{sid}-") and len(name) == len(sid) + 13
    assert safe_name("637f20cafde22ff8") == "637f20cafde22ff8"
    assert safe_name("scene-0061") == "scene-0061"


@pytest.mark.sumo
def test_a_scene_named_summary_csv_converts_beside_the_summary(tmp_path):
    """Real WOMD scenes renamed ``summary.csv`` and two others convert in one batch: three
    bundles and convert's own summary, nothing in each other's place."""
    from converters.tfrecord import iter_records, write_records
    from converters.womd.protos import scenario_pb2 as pb
    from magail_sumo.cli.main import main

    raw = next(d for _, d in iter_records(ROOT / "data" / "womd" / "850c48d8bbfa008f.tfrecord"))

    def renamed(sid: str) -> bytes:
        s = pb.Scenario()
        s.ParseFromString(raw)
        s.scenario_id = sid
        return s.SerializeToString()

    write_records(tmp_path / "batch.tfrecord", [renamed(s) for s in ("a1", "summary.csv")])
    assert main(["convert", str(tmp_path / "batch.tfrecord"), "--out", str(tmp_path / "cv"),
                 "--no-baseline"]) == 0
    cv = tmp_path / "cv"
    assert (cv / "summary.csv").is_file() and (cv / "a1").is_dir()
    assert [p.name for p in cv.iterdir() if p.name.startswith("summary.csv-")]


def test_a_killed_commands_marker_temp_file_does_not_lock_the_folder(tmp_path):
    """A command killed while writing its marker leaves ``..magail_sumo.json.XXXX.tmp``; the
    folder is still claimable (the file left alone), while any other file still refuses it."""
    from magail_sumo.outputs import claim_output_dir

    d = tmp_path / "out"
    d.mkdir()
    tmp = d / "..magail_sumo.json.k2j_9x.tmp"
    tmp.write_text('{"tools": {"evaluate": ["manifest.json"]}}')
    claim_output_dir(d, "evaluate", ["manifest.json"])
    assert (d / MARKER).is_file() and tmp.read_text().startswith("{")
    other = tmp_path / "other"
    other.mkdir()
    (other / "..magail_sumo.json.k2j_9x.tmp").write_text("{}")
    (other / "precious.txt").write_text("x")
    with pytest.raises(OutputError, match="not empty"):
        claim_output_dir(other, "evaluate")
