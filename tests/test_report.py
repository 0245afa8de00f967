"""magail-sumo report: HTML/Markdown/CSV, rendered in headless Chromium; bad rollouts reported."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from conftest import ROOT, WOMD_DIR
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
    # speed bias (simulated - logged mean speed, m/s): 0 for log replay, in both tables
    assert summary.set_index("method").loc["logreplay", "speed_bias"] == pytest.approx(0, abs=1e-6)
    assert np.isfinite(metrics["speed_bias"]).all()
    md = (rep / "report.md").read_text()
    assert "| constvel |" in md and "![" in md
    # paired bootstrap comparison over the two scenes: log replay is more realistic on both
    diff = metrics.pivot(index="scenario_id", columns="method", values="metametric")
    assert (diff["logreplay"] > diff["constvel"]).all()
    row = next(line for line in md.splitlines() if line.startswith("| constvel − logreplay |"))
    assert "| 2 |" in row and row.rstrip(" |").endswith("logreplay better than constvel")
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
                                   "--virtual-time-budget=2500", page.as_uri()],
                         capture_output=True, text=True, timeout=120).stdout
    assert "<table" in dom
    for m in METHODS:
        assert re.search(rf"<tr><td>{m}</td>", dom), m
    imgs = re.findall(r'<img[^>]+src="data:image/png;base64,', dom)
    assert len(imgs) >= 2 + len(SCENES)  # bars, distributions, one overlay per scene
    # the animated views ran: one player per scene, past its first frame, a canvas per panel
    frames = dict(re.findall(r'<div class="anim" data-scene="([^"]+)" data-frame="(\d+)"', dom))
    assert set(frames) == set(SCENES) and all(int(f) > 0 for f in frames.values()), frames
    assert dom.count("<canvas") == len(SCENES) * (1 + len(METHODS))
    assert '<table class="agents">' in dom
    shot = tmp_path / "shot.png"
    subprocess.run(common + [f"--user-data-dir={tmp_path / 'p2'}", f"--screenshot={shot}",
                             "--window-size=1200,1600", page.as_uri()],
                   capture_output=True, timeout=120)
    import matplotlib.pyplot as plt

    pix = plt.imread(shot)
    assert pix.shape[0] >= 1000 and pix[..., :3].std() > 0.05  # not blank


@pytest.mark.parametrize("width", [1280, 1920])
def test_report_fits_the_page_with_no_overlap_and_every_image_loaded(folder, width):
    """At common widths no element is wider than the page (wide tables scroll inside their own
    box), no two text boxes overlap, and every image loaded."""
    from magail_sumo.evaluation.report.layout import check_layout

    got = check_layout(folder / "report" / "report.html", width, _chromium())
    assert got["width"] >= width - 20
    assert got["page"] <= got["width"], f"the page scrolls sideways: {got['page']} px"
    assert got["wide"] == [] and got["overlaps"] == [] and got["broken"] == [], got


def test_bar_chart_labels_never_overlap():
    """Long method names and many panels: tick labels and titles keep apart."""
    from matplotlib.transforms import Bbox

    from magail_sumo.evaluation.report import figures

    methods = ["logreplay", "constvel", "sumo", "pretrained:decomposed_social_womd14",
               "a_very_long_method_name_from_a_checkpoint_path"]
    fields = ["metametric", "ade", "collision_rate", "offroad_rate", "hard_braking_rate",
              "route_completion", "speed_js", "ttc_js"]
    rng = np.random.default_rng(0)
    means = {m: {f: float(rng.random()) for f in fields} for m in methods}
    cis = {m: {f: 0.1 for f in fields} for m in methods}
    fig = figures.bar_chart_figure(means, fields, {"ade": "m"}, "Methods compared", cis)
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    texts = [t for ax in fig.axes for t in (*ax.get_yticklabels(), *ax.get_xticklabels(),
                                             ax.title) if t.get_visible() and t.get_text()]
    boxes = [t.get_window_extent(r) for t in texts]
    page = Bbox([[0, 0], [fig.bbox.width, fig.bbox.height]])
    for k, (a, ta) in enumerate(zip(boxes, texts)):
        assert page.contains(a.x0 + 1, a.y0 + 1) and page.contains(a.x1 - 1, a.y1 - 1), \
            f"{ta.get_text()!r} is cut off"
        for b, tb in zip(boxes[k + 1:], texts[k + 1:]):
            inter = Bbox.intersection(a, b)
            assert inter is None or inter.width < 1 or inter.height < 1, \
                f"{ta.get_text()!r} overlaps {tb.get_text()!r}"
    import matplotlib.pyplot as plt

    plt.close(fig)
    svg = figures.bar_chart(means, fields, {}, "t", cis).svg
    assert svg.lstrip().startswith(b"<?xml") and b"<svg" in svg


def test_confidence_intervals():
    from magail_sumo.evaluation.report.intervals import mean_ci, t975, with_ci

    assert t975(1) == 12.706 and abs(t975(100) - 1.984) < 1e-3
    m, h = mean_ci([1.0, 2.0, 3.0, float("nan")])
    assert m == 2.0 and abs(h - 4.303 * 1.0 / 3 ** 0.5) < 1e-9
    assert np.isnan(mean_ci([5.0])[1]) and np.isnan(mean_ci([])[0])
    assert with_ci(0.61234, 0.031) == "0.6123 ± 0.031" and with_ci(1.0, float("nan")) == "1"


def test_invalid_states_never_drawn(folder):
    """Issue 14: log replay carries (0, 0) at the log's invalid states; neither the static
    panels nor the animated view draw a vertex there (NaN breaks the lines / null)."""
    from magail_sumo.evaluation.report import animation, figures
    from magail_sumo.evaluation.report.scoring import collect

    sc = collect(folder)
    sid = SCENES[0]
    ro, valid = sc.rollouts[(sid, "logreplay")], sc.valid[(sid, "logreplay")]
    assert (~valid).any()
    pts = lambda x, y: set(zip(np.asarray(x, float).tolist(), np.asarray(y, float).tolist()))  # noqa: E731
    bad = pts(ro.x[~valid], ro.y[~valid]) - pts(ro.x[valid], ro.y[valid])
    tr = sc.scenes[sid].tracks
    bad_log = pts(tr.x[~tr.valid], tr.y[~tr.valid]) - pts(tr.x[tr.valid], tr.y[tr.valid])
    assert (0.0, 0.0) in bad and bad_log
    fig = figures.trajectory_figure(sc, sid)
    drawn = set()
    for ax in fig.axes:
        for line in ax.get_lines():
            xy = line.get_xydata()
            xy = xy[np.isfinite(xy).all(1)]
            drawn |= pts(xy[:, 0], xy[:, 1])
        for coll in ax.collections:
            off = coll.get_offsets()
            drawn |= pts(off[:, 0], off[:, 1])
    assert drawn and not drawn & (bad | bad_log)
    data = animation.scene_data(sc, sid)
    panel = next(p for p in data["panels"] if p["name"] == "logreplay")
    for a in range(ro.shape[1]):
        xs = panel["x"][a][1:]
        assert all(x is None for x, v in zip(xs, valid[0, a]) if not v)
        assert all(x is not None for x, v in zip(xs, valid[0, a]) if v)
    log = data["panels"][0]
    rows = [int(np.flatnonzero(tr.id == i)[0]) for i in ro.object_id]
    cur = sc.scenes[sid].current_time_index
    for a, r in enumerate(rows):
        v = tr.valid[r, cur:cur + 1 + ro.shape[2]]
        assert [x is not None for x in log["x"][a][:len(v)]] == v.tolist()


def test_scoring_workers_draw_the_same_views(folder):
    """Each scoring worker draws the trajectory figure and animation of its scenes: the same
    bytes as the report draws itself (it falls back to that for the other scenes)."""
    from magail_sumo.evaluation.report import animation, figures
    from magail_sumo.evaluation.report.scoring import collect

    calls = []
    sc = collect(folder, workers=2, progress=lambda *c: calls.append(c))
    pairs = len(SCENES) * len(sc.methods)
    assert calls[-1] == ("scored", pairs, pairs) and all(c[0] == "scored" for c in calls)
    serial = []
    collect(folder, workers=1, progress=lambda *c: serial.append(c))
    assert serial == [("scored", k, pairs) for k in range(1, pairs + 1)]
    assert set(sc.views) == set(SCENES)
    for sid, view in sc.views.items():
        assert view.methods == tuple(sc.methods)
        assert view.trajectories_png == figures.trajectories(sc, sid)
        assert view.animation_html == animation.scene_animation(sc, sid)
    # a view of other methods (an external submission scored later) is drawn again
    from magail_sumo.evaluation.report import _view
    from magail_sumo.evaluation.report.scoring import SceneView

    sid = SCENES[0]
    sc.views[sid] = SceneView(("elsewhere",), b"", "")
    assert _view(sc, sid).trajectories_png == figures.trajectories(sc, sid)


def test_scoring_jobs_are_balanced():
    from magail_sumo.evaluation.report.scoring import plan_jobs

    costs = {"a": 15.0, "b": 50.0, "c": 4.0, "d": 66.0, "e": 25.0}
    jobs = plan_jobs(costs, ["m1", "m2", "m3"], 2)
    assert len(jobs) == 2 and all(ms == ["m1", "m2", "m3"] for job in jobs for _, ms in job)
    assert sorted(sid for job in jobs for sid, _ in job) == sorted(costs)
    loads = [sum(costs[sid] for sid, _ in job) for job in jobs]
    assert max(loads) - min(loads) <= 4.0
    # fewer scenes than workers: the scene's methods are split
    assert plan_jobs({"a": 1.0}, ["m1", "m2", "m3"], 2) == [[("a", ["m1", "m2"])],
                                                            [("a", ["m3"])]]
    assert plan_jobs({"a": 1.0}, ["m1"], 4) == [[("a", ["m1"])]]


def test_agent_table_and_named_method(folder, tmp_path):
    """Issue 14: the per-agent realism table (HTML and agents.csv) and a policy named with
    ``evaluate --name`` reported under that name."""
    dst = _copy(folder, tmp_path)
    assert main(["evaluate", "--policy", "constvel", "--name", "cv_named", "--baselines", "none",
                 "--scenes", *(str(WOMD_DIR / f"{s}.tfrecord") for s in SCENES),
                 "--rollouts", "2", "--out", str(dst)]) == 0
    assert main(["report", str(dst)]) == 0
    rep = dst / "report"
    assert list(pd.read_csv(rep / "summary.csv").method) == [*METHODS, "cv_named"]
    agents = pd.read_csv(rep / "agents.csv")
    n_eval = {"637f20cafde22ff8": 4, "850c48d8bbfa008f": 1}  # SDC + tracks to predict
    assert len(agents) == sum(n_eval.values()) * (len(METHODS) + 1)
    assert agents.groupby("scenario_id").object_id.nunique().to_dict() == n_eval
    assert agents.sdc.sum() == len(SCENES) * (len(METHODS) + 1)
    lr = agents[agents.method == "logreplay"]
    assert (lr.ade == 0).all() and (lr.min_ade == 0).all()
    cv = agents[agents.method == "constvel"].set_index(["scenario_id", "object_id"])
    named = agents[agents.method == "cv_named"].set_index(["scenario_id", "object_id"])
    pd.testing.assert_frame_equal(cv.drop(columns="method"), named.drop(columns="method"))
    lik = agents.filter(like="_likelihood").to_numpy()
    assert ((lik[np.isfinite(lik)] > 0) & (lik[np.isfinite(lik)] <= 1)).all()
    page = (rep / "report.html").read_text()
    assert '<table class="agents">' in page and "<td>cv_named</td>" in page


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


def test_scene_with_another_current_step_is_scored():
    """A scene whose current step is not 10 (ScenarioNet scenes with a longer or shorter
    history) is scored on its own 80 simulated steps instead of failing the report."""
    import dataclasses

    from magail_sumo.evaluation.report.scoring import score_pair

    scene = load_scene(WOMD_DIR / "850c48d8bbfa008f.tfrecord")
    scene = dataclasses.replace(scene, current_time_index=5)
    res = score_pair(scene, "logreplay", log_replay(scene, 2))
    assert res.error is None, res.error
    assert res.row["ade"] == 0.0 and res.row["average_displacement_error"] == 0.0
    assert 0 < res.row["metametric"] <= 1 and res.agent_rows
    assert sum(res.counts["linear_speed"][0]) > 0


def test_recorded_scenes_road_edges_agree(folder):
    """The bundled WOMD scenes: the log's own off-road share and count are in metrics.csv;
    850c's 2 of 4 vehicles off the road are too few to call its map wrong, so the report gives
    no off-road figures apart."""
    rows = pd.read_csv(folder / "report" / "metrics.csv")
    assert ((rows["log_offroad_rate"] < 0.2) | (rows["log_offroad_vehicles"] < 3)).all()
    assert "Road edges that disagree" not in (folder / "report" / "report.md").read_text()


SHARED_VQA = Path(os.environ.get("MAGAIL_SUMO_SHARED_DATA", ROOT.parent / "shared" / "data")) \
    / "scenarionet" / "womd_metavqa" / "sd_adv_reconstructed_v0_1bc6a4b9033b6746_random_adv.pkl"


@pytest.mark.skipif(not SHARED_VQA.is_file(), reason="no shared MetaVQA data")
def test_scene_whose_road_edges_disagree_with_its_log_is_reported_apart(tmp_path):
    """A MetaVQA scene whose map puts almost every recorded vehicle off the road edges (the
    data README's caution): the report names it with the log's share and gives off-road rates
    on agreeing and disagreeing scenes apart."""
    out = tmp_path / "eval"
    assert main(["evaluate", "--policy", "constvel", "--baselines", "logreplay", "--scenes",
                 str(SHARED_VQA), str(WOMD_DIR / "850c48d8bbfa008f.tfrecord"), "--rollouts", "2",
                 "--out", str(out)]) == 0
    assert main(["report", str(out)]) == 0
    md = (out / "report" / "report.md").read_text()
    assert "Road edges that disagree with the log: in 1 of 2 scene(s)" in md
    assert re.search(r"1bc6a4b9033b6746_random_adv 0\.9\d", md)
    assert "| method | agreeing scenes (1) | disagreeing scenes (1) |" in md
