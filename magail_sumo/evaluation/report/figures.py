"""Report figures (matplotlib, Agg backend): :class:`Figure` (PNG and SVG), the scenes'
trajectories as PNG bytes."""

from __future__ import annotations

import io
from dataclasses import dataclass

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from magail_sumo.evaluation.traffic.distributions import BINS  # noqa: E402
from magail_sumo.outputs import printable  # noqa: E402

from .scores import Scores  # noqa: E402

COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2")


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)  # laid out by tight_layout: no second draw pass
    plt.close(fig)
    return buf.getvalue()


@dataclass(frozen=True)
class Figure:
    """A drawn report figure: PNG (inlined in the HTML) and SVG (a vector copy for papers,
    written beside the PNG)."""

    png: bytes
    svg: bytes


def _figure(fig) -> Figure:
    buf = io.BytesIO()
    fig.savefig(buf, format="svg")
    svg = buf.getvalue()
    return Figure(_png(fig), svg)


#: the method whose figures are the recording's own (the reference, drawn grey)
REFERENCE = "logreplay"


def _method_colors(methods: list[str]) -> list[str]:
    out, k = [], 0
    for m in methods:
        if m == REFERENCE:
            out.append("#999999")
        else:
            out.append(COLORS[k % len(COLORS)])
            k += 1
    return out


def bar_chart_figure(means: dict[str, dict[str, float]], fields: list[str],
                     units: dict[str, str], title: str,
                     cis: dict[str, dict[str, float]] | None = None):
    """The matplotlib figure of :func:`bar_chart` (for tests: its labels' extents)."""
    methods = list(means)
    n = len(fields)
    cols = min(4, n)
    rows = (n + cols - 1) // cols
    longest = max((len(m) for m in methods), default=1)
    height = 0.9 + 0.28 * max(1, len(methods))
    fig, axes = plt.subplots(rows, cols, figsize=(2.4 * cols + 0.07 * longest, height * rows),
                             squeeze=False, sharey=True)
    colors = _method_colors(methods)
    ypos = np.arange(len(methods))[::-1]
    for ax, f in zip(axes.ravel(), fields):
        vals = np.array([means[m][f] for m in methods], np.float64)
        err = None if cis is None else np.array([cis[m][f] for m in methods], np.float64)
        ax.barh(ypos, np.nan_to_num(vals), color=colors, height=0.7,
                xerr=None if err is None else np.nan_to_num(err), ecolor="#333333",
                capsize=2, error_kw={"lw": 0.8})
        ax.set_yticks(ypos, methods, fontsize=7)
        unit = units.get(f, "")
        ax.set_title(f"{f}" + (f" ({unit})" if unit else ""), fontsize=8)
        ax.tick_params(axis="x", labelsize=6)
        ax.xaxis.set_major_locator(plt.MaxNLocator(3, prune="upper"))  # clear of the next panel
        lo = np.nanmin(np.concatenate([[0.0], vals - (0 if err is None else np.nan_to_num(err))]))
        if np.isfinite(lo) and lo >= 0:
            ax.set_xlim(left=0)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    note = " (bars: mean over scenes, whiskers: 95 % interval)" if cis is not None else ""
    fig.suptitle(title + note, fontsize=9)
    fig.tight_layout(w_pad=4.0)
    return fig


def bar_chart(means: dict[str, dict[str, float]], fields: list[str], units: dict[str, str],
              title: str, cis: dict[str, dict[str, float]] | None = None) -> Figure:
    """One small horizontal-bar panel per field, one bar per method (names on the shared
    y axis, never rotated or overlapping), whiskers the 95 % interval over scenes (``cis``:
    half-widths); the log-replay reference is grey."""
    return _figure(bar_chart_figure(means, fields, units, title, cis))


def _at_cap(hist: np.ndarray) -> float:
    return float(hist[-1] / max(hist.sum(), 1.0))


def distributions(scores: Scores, features: list[tuple[str, str]]) -> Figure:
    """Log vs each method's histograms (pooled over scenes) of the given (feature, label).

    Time to collision is capped (5 s: no conflict ahead) and most of its mass sits in the
    cap's bin, which would flatten the rest: its panel shows the distribution below the cap
    (each curve normalised over its values below the cap) and the share at the cap in the
    legend."""
    fig, axes = plt.subplots(1, len(features), figsize=(4.2 * len(features), 3.2),
                             squeeze=False)
    colors = _method_colors(scores.methods)
    for ax, (feat, label) in zip(axes[0], features):
        lo, hi, n = BINS[feat]
        centres = lo + (np.arange(n) + 0.5) * (hi - lo) / n
        capped = feat == "time_to_collision"
        keep = slice(0, n - 1) if capped else slice(0, n)
        log_by_scene: dict[str, np.ndarray] = {}
        for k, m in enumerate(scores.methods):
            sims = []
            for (sid, mm), counts in scores.counts.items():
                if mm == m and feat in counts:
                    lc, sc = counts[feat]
                    sims.append(sc)
                    log_by_scene.setdefault(sid, lc)
            if sims:  # pooled over scenes: the summed counts, normalised
                h = np.sum(sims, axis=0).astype(np.float64)
                name = m + (f" ({_at_cap(h):.0%} at cap)" if capped else "")
                ax.plot(centres[keep], h[keep] / max(h[keep].sum(), 1.0), color=colors[k],
                        label=name, lw=1.3)
        if log_by_scene:
            h = np.sum(list(log_by_scene.values()), axis=0).astype(np.float64)
            name = "log" + (f" ({_at_cap(h):.0%} at cap)" if capped else "")
            ax.plot(centres[keep], h[keep] / max(h[keep].sum(), 1.0), "k--", label=name,
                    lw=1.6)
        ax.set_title(label + (f", below the {hi:g}-s cap" if capped else ""), fontsize=9)
        ax.set_ylabel("share", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6)
    fig.tight_layout()
    return _figure(fig)


def _joined(x: np.ndarray, y: np.ndarray, valid: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """Lines (rows of ``x``/``y``, (L, T)) joined into one NaN-separated polyline; states not
    ``valid`` become NaN, so a line breaks there and no vertex is drawn at them."""
    x = np.asarray(x, np.float64).reshape(-1, np.shape(x)[-1])
    y = np.asarray(y, np.float64).reshape(-1, np.shape(y)[-1])
    if valid is not None:
        v = np.asarray(valid, bool).reshape(x.shape)
        x, y = np.where(v, x, np.nan), np.where(v, y, np.nan)
    gap = np.full((x.shape[0], 1), np.nan)
    return np.hstack([x, gap]).ravel(), np.hstack([y, gap]).ravel()


def _polylines(lines: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Map polylines ((P, >=2) arrays) as one NaN-separated polyline."""
    if not lines:
        return np.zeros(0), np.zeros(0)
    gap = np.full((1, 2), np.nan)
    xy = np.concatenate([a for ln in lines for a in (np.asarray(ln)[:, :2], gap)])
    return xy[:, 0], xy[:, 1]


def trajectory_figure(scores: Scores, sid: str, max_rollouts: int = 8):
    """The matplotlib figure of :func:`trajectories` (for tests: every line is one
    NaN-separated ``Line2D``; invalid log and rollout states are NaN, never drawn)."""
    scene = scores.scenes[sid]
    methods = [m for m in scores.methods if (sid, m) in scores.rollouts]
    fig, axes = plt.subplots(1, max(1, len(methods)), figsize=(3.6 * max(1, len(methods)), 3.6),
                             squeeze=False)
    tr = scene.tracks
    cur = scene.current_time_index
    lanes = _polylines([ln.polyline for ln in scene.roadmap.lanes])
    edges = _polylines([e.polyline for e in scene.roadmap.road_edges])
    for k, (ax, m) in enumerate(zip(axes[0], methods)):
        ro = scores.rollouts[(sid, m)]
        ax.plot(*lanes, color="#cccccc", lw=0.5)
        ax.plot(*edges, color="#333333", lw=0.8)
        rows = np.array([int(np.flatnonzero(tr.id == i)[0]) for i in ro.object_id])
        fut = slice(cur, cur + 1 + ro.shape[2])
        ax.plot(*_joined(tr.x[rows, fut], tr.y[rows, fut], tr.valid[rows, fut]), "k--", lw=0.8)
        n = min(max_rollouts, ro.shape[0])
        valid = scores.valid.get((sid, m))
        ax.plot(*_joined(ro.x[:n], ro.y[:n], None if valid is None else valid[:n]),
                color=COLORS[k % 7], lw=0.6, alpha=0.5)
        v = tr.valid[rows, cur]
        xs, ys = tr.x[rows, cur][v], tr.y[rows, cur][v]
        ax.scatter(xs, ys, s=6, color="k", zorder=3)
        if xs.size:
            pad = 25.0
            ax.set_xlim(xs.min() - pad, xs.max() + pad)
            ax.set_ylim(ys.min() - pad, ys.max() + pad)
        ax.set_aspect("equal")
        ax.set_title(f"{m}", fontsize=9)
        ax.set_xticks([])  # scene coordinates say nothing; ticks cost most of the drawing
        ax.set_yticks([])
    x0, x1 = axes[0][0].get_xlim()
    fig.suptitle(f"{printable(sid, 60)}: log (dashed) vs rollouts (panels {x1 - x0:.0f} m wide)",
                 fontsize=10)
    fig.subplots_adjust(left=0.02, right=0.98, bottom=0.02, top=0.86, wspace=0.05)
    return fig


def trajectories(scores: Scores, sid: str, max_rollouts: int = 8) -> bytes:
    """Top-down view of one scene: lanes (grey), road edges (black), recorded futures (black
    dashed) and the rollouts (colour) of every method, one panel per method; states a method or
    the log marks invalid are not drawn (the lines break there)."""
    return _png(trajectory_figure(scores, sid, max_rollouts))


def city_figure(runs: dict[str, dict], scenario: str) -> Figure:
    """One city scenario, one colour per method (SUMO's default drivers grey): vehicles in the
    network over the window, the distribution of completed trips' travel times, and of the
    edges' mean speeds weighted by the time vehicles spent on them (``runs``: method ->
    :func:`~magail_sumo.evaluation.traffic.sumo_outputs.run_distributions`)."""
    fig, axes = plt.subplots(1, 3, figsize=(12.6, 3.2), squeeze=False)
    ax_n, ax_t, ax_v = axes[0]
    methods = list(runs)
    colors = ["#999999" if m == "sumo" else COLORS[k % len(COLORS)]
              for k, m in enumerate(methods)]
    times = np.concatenate([r["travel_time_s"] for r in runs.values()] or [np.zeros(0)])
    t_edges = np.histogram_bin_edges(times, bins=30) if times.size else np.linspace(0, 1, 2)
    for m, c in zip(methods, colors):
        r = runs[m]
        if r["time_s"].size:
            ax_n.plot(r["time_s"] - r["time_s"][0], r["running"], color=c, lw=1.2, label=m)
        if r["travel_time_s"].size:
            ax_t.hist(r["travel_time_s"], bins=t_edges, histtype="step", color=c, lw=1.3,
                      label=f"{m} ({r['travel_time_s'].size} trips)")
        v, w = r["edge_speed_mps"]
        if v.size and w.sum() > 0:
            ax_v.hist(v, bins=np.linspace(0, max(15.0, float(np.nanmax(v))), 31), weights=w,
                      density=True, histtype="step", color=c, lw=1.3, label=m)
    ax_n.set_title("vehicles in the network", fontsize=9)
    ax_n.set_xlabel("time in the window (s)", fontsize=8)
    ax_t.set_title("travel time of completed trips", fontsize=9)
    ax_t.set_xlabel("s", fontsize=8)
    ax_v.set_title("edge mean speed (time-weighted)", fontsize=9)
    ax_v.set_xlabel("m/s", fontsize=8)
    return _city_panels(fig, axes[0], f"city {printable(scenario, 60)}")


def _city_panels(fig, axes, title: str) -> Figure:
    """A city figure's panels finished alike: small ticks, a legend where there are labels,
    the title."""
    for ax in axes:
        ax.tick_params(labelsize=7)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _figure(fig)


def kinematics_figure(kin: dict, scenario: str) -> Figure:
    """One city scenario's speed and 1-s acceleration distributions: the recorded humans
    (black), each method's drivers (SUMO's grey); ``kin``: its ``kinematics.json``
    (:mod:`~magail_sumo.evaluation.city_kinematics`)."""
    fig, axes = plt.subplots(1, 2, figsize=(9.0, 3.0), squeeze=False)
    groups = dict(kin.get("methods") or {})
    if kin.get("humans"):
        groups = {"recorded humans": kin["humans"], **groups}
    for ax, (name, unit) in zip(axes[0], (("speed", "m/s"), ("accel", "m/s²"))):
        lo, hi, n = kin["bins"][name]
        edges = np.linspace(lo, hi, n + 1)
        for k, (m, g) in enumerate(groups.items()):
            c = np.asarray((g or {}).get(name, []), np.float64)
            if c.size != n or c.sum() <= 0:
                continue
            color = "#000000" if m == "recorded humans" else \
                "#999999" if m == "sumo" else COLORS[k % len(COLORS)]
            ax.stairs(c / c.sum(), edges, color=color, lw=1.3, label=printable(m, 30))
        ax.set_title(f"{'speed' if name == 'speed' else 'acceleration over 1 s'}", fontsize=9)
        ax.set_xlabel(unit, fontsize=8)
        ax.set_ylabel("share of samples", fontsize=8)
    return _city_panels(fig, axes[0],
                        f"city {printable(scenario, 60)}: drivers against recorded humans")
