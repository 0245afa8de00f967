"""magail-sumo report: HTML/Markdown/CSV, rendered in headless Chromium; bad rollouts reported."""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pandas as pd
import pytest

from conftest import WOMD_DIR
from magail_sumo.cli.main import main
from magail_sumo.evaluation.realism import log_replay
from magail_sumo.evaluation.submission import write_submission
from converters import load_scene

SCENES = ("637f20cafde22ff8", "850c48d8bbfa008f")
METHODS = ("constvel", "logreplay")


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("evalrep")
    rc = main(["evaluate", "--policy", "constvel", "--baselines", "logreplay", "--scenes",
               *(str(WOMD_DIR / f"{s}.tfrecord") for s in SCENES), "--rollouts", "2",
               "--out", str(out)])
    assert rc == 0
    assert main(["report", str(out)]) == 0
    return out


def test_report_files(folder):
    rep = folder / "report"
    summary = pd.read_csv(rep / "summary.csv")
    assert list(summary.method) == list(METHODS)
    assert summary.set_index("method").loc["logreplay", "ade"] == 0.0
    metrics = pd.read_csv(rep / "metrics.csv")
    assert len(metrics) == len(SCENES) * len(METHODS) and "metametric" in metrics
    md = (rep / "report.md").read_text()
    assert "| constvel |" in md and "![" in md
    for img in re.findall(r"\]\((img/[^)]+)\)", md):
        assert (rep / img).stat().st_size > 1000


def _chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("chromium not installed (.ci/run installs it)")
    return exe


def test_report_renders_in_headless_chromium(folder, tmp_path):
    exe = _chromium()
    page = (folder / "report" / "report.html").resolve()
    common = [exe, "--headless", "--no-sandbox", "--disable-gpu",
              "--disable-background-networking", "--disable-component-update", "--disable-sync",
              "--no-first-run", "--disable-dev-shm-usage"]
    dom = subprocess.run(common + [f"--user-data-dir={tmp_path / 'p1'}", "--dump-dom",
                                   page.as_uri()],
                         capture_output=True, text=True, timeout=120).stdout
    assert "<table" in dom
    for m in METHODS:
        assert re.search(rf"<tr><td>{m}</td>", dom), m
    imgs = re.findall(r'<img[^>]+src="data:image/png;base64,', dom)
    assert len(imgs) >= 2 + len(SCENES)  # bars, distributions, one overlay per scene
    shot = tmp_path / "shot.png"
    subprocess.run(common + [f"--user-data-dir={tmp_path / 'p2'}", f"--screenshot={shot}",
                             "--window-size=1200,1600", page.as_uri()],
                   capture_output=True, timeout=120)
    import matplotlib.pyplot as plt

    pix = plt.imread(shot)
    assert pix.shape[0] >= 1000 and pix[..., :3].std() > 0.05  # not blank


def _copy(folder, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(folder, dst, ignore=shutil.ignore_patterns("report"))
    return dst


def test_bad_rollouts_are_reported_and_others_scored(folder, tmp_path, capsys):
    dst = _copy(folder, tmp_path)
    a, b = SCENES
    p = dst / "rollouts" / "constvel" / f"{a}.parquet"
    df = pd.read_parquet(p)
    victim = int(df.object_id.iloc[0])
    df.loc[(df.object_id == victim) & (df.step == 30), "x"] = np.nan  # NaN position
    df.to_parquet(p)
    q = dst / "rollouts" / "logreplay" / f"{b}.parquet"
    dq = pd.read_parquet(q)
    dropped = int(dq.object_id.iloc[0])
    dq[dq.object_id != dropped].to_parquet(q)  # wrong agent set
    p2 = dst / "rollouts" / "logreplay" / f"{a}.parquet"
    d2 = pd.read_parquet(p2)
    d2[d2.step < 90].to_parquet(p2)  # 79 simulated steps
    scene = load_scene(WOMD_DIR / f"{a}.tfrecord")
    other = log_replay(load_scene(WOMD_DIR / "2831b6fde0420b0d.tfrecord"), 2)
    sub = tmp_path / "ext.binproto"
    write_submission(sub, [log_replay(scene, 2), other])
    rc = main(["report", str(dst), "--submission", "ext", str(sub)])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("error:")]
    assert rc == 1 and len(err) == 4, err
    assert any(f"scenario {a}" in e and f"agent {victim}" in e and "non-finite x" in e
               for e in err)
    assert any(f"scenario {b}" in e and "wrong agent set" in e and str(dropped) in e
               for e in err)
    assert any(f"scenario {a}" in e and "79 simulated steps" in e for e in err)
    assert any("2831b6fde0420b0d" in e and "not among the evaluated scenes" in e for e in err)
    metrics = pd.read_csv(dst / "report" / "metrics.csv")
    got = set(zip(metrics.scenario_id, metrics.method))
    assert got == {(b, "constvel"), (a, "ext")}
    assert "Problems" in (dst / "report" / "report.html").read_text()
