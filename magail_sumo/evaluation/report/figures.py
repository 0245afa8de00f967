"""Report figures (matplotlib, Agg backend) returned as PNG bytes."""

from __future__ import annotations

import io

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


def bar_chart(means: dict[str, dict[str, float]], fields: list[str], units: dict[str, str],
              title: str) -> bytes:
    """One small bar panel per field, one bar per method."""
    methods = list(means)
    n = len(fields)
    cols = min(4, n)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.4 * rows), squeeze=False)
    for ax, f in zip(axes.ravel(), fields):
        vals = [means[m][f] for m in methods]
        ax.bar(range(len(methods)), np.nan_to_num(vals), color=COLORS[:len(methods)])
        ax.set_xticks(range(len(methods)), methods, rotation=30, fontsize=7)
        ax.set_title(f"{f} ({units.get(f, '')})", fontsize=8)
        ax.tick_params(axis="y", labelsize=7)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _png(fig)


def distributions(scores: Scores, features: list[tuple[str, str]]) -> bytes:
    """Log vs each method's histograms (pooled over scenes) of the given (feature, label)."""
    fig, axes = plt.subplots(1, len(features), figsize=(4.2 * len(features), 3.0),
                             squeeze=False)
    for ax, (feat, label) in zip(axes[0], features):
        lo, hi, n = BINS[feat]
        centres = lo + (np.arange(n) + 0.5) * (hi - lo) / n
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
                ax.plot(centres, h / max(h.sum(), 1.0), color=COLORS[k % 7], label=m, lw=1.3)
        if log_by_scene:
            h = np.sum(list(log_by_scene.values()), axis=0).astype(np.float64)
            ax.plot(centres, h / max(h.sum(), 1.0), "k--", label="log", lw=1.6)
        ax.set_title(label, fontsize=9)
        ax.set_ylabel("share", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    return _png(fig)


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
