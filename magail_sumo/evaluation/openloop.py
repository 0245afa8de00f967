"""Open-loop motion-prediction metrics of a GameFormer checkpoint, per level k.

Windows: every current step ``c = history_steps − 1, + eval_stride, …`` of a scene with the
full ``future_steps`` future inside the scene; focal agents: objects of the run's
``focal_types`` observed at ``c`` and at ``c + future_steps`` (as WOMD requires a valid last
step). Each focal agent is predicted in its own sample (:func:`~magail_sumo.models.gameformer_features.build_sample`,
the recorded history) and scored on its M modes at every level 0..K:

* minADE: the smallest over the modes of the mean displacement (m) over the observed future
  steps; minFDE: the smallest displacement at the last step.
* miss rate at 3, 5 and 8 s (Waymo's definition): the prediction misses at horizon t when no
  mode lies within the longitudinal and lateral thresholds of the ground truth at t (the
  displacement rotated into the ground truth's heading at t); thresholds (lat, lon) = (1.0,
  2.0), (1.8, 3.6), (3.0, 6.0) m at 3 / 5 / 8 s, scaled by 0.5 below 1.4 m/s current speed, 1
  above 11 m/s, linearly in between. A horizon where the ground truth is unobserved is not
  scored. ``miss_rate`` is the mean over the three horizons.
* overlap rate: the share of focal agents whose most likely mode (highest score), as a box of
  the agent's current size centred on the predicted position with the agent's recorded heading
  at that step (where unrecorded, the heading along the predicted path), overlaps the recorded
  box of any other object observed at the same step (:func:`~magail_sumo.evaluation.realism.interaction.signed_box_distance`
  < 0) at any future step.

The constant-velocity prediction (one mode) is scored the same way for reference.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from converters import iter_scenes
from magail_sumo.evaluation.realism.interaction import signed_box_distance
from magail_sumo.models.gameformer_features import (Frame, build_sample, collate, focal_types,
                                                    log_future, log_history, map_chunks)
from magail_sumo.scene import Scene

#: (horizon s, step index into the future, lateral m, longitudinal m)
MISS_HORIZONS = ((3, 29, 1.0, 2.0), (5, 49, 1.8, 3.6), (8, 79, 3.0, 6.0))
SPEED_LOW, SPEED_HIGH, SCALE_LOW = 1.4, 11.0, 0.5
METRICS = ("min_ade", "min_fde", "miss_rate_3s", "miss_rate_5s", "miss_rate_8s", "miss_rate",
           "overlap_rate")


def speed_scale(speed: np.ndarray) -> np.ndarray:
    """Waymo's threshold scale: 0.5 below 1.4 m/s, 1 above 11 m/s, linear in between."""
    frac = np.clip((np.asarray(speed) - SPEED_LOW) / (SPEED_HIGH - SPEED_LOW), 0.0, 1.0)
    return SCALE_LOW + (1.0 - SCALE_LOW) * frac


def misses(pred: np.ndarray, gt: np.ndarray, gt_heading: np.ndarray, valid: np.ndarray,
           speed: np.ndarray) -> np.ndarray:
    """(S, H) miss (1.0), hit (0.0) or unscored (NaN) per sample and horizon of
    :data:`MISS_HORIZONS`.

    :param pred: (S, M, T, 2). :param gt: (S, T, 2). :param gt_heading: (S, T) rad (same
        frame). :param valid: (S, T). :param speed: (S,) m/s at the current step.
    """
    scale = speed_scale(speed)
    out = np.full((len(gt), len(MISS_HORIZONS)), np.nan)
    for h, (_, t, lat, lon) in enumerate(MISS_HORIZONS):
        d = pred[:, :, t] - gt[:, None, t]  # (S, M, 2)
        c, s = np.cos(gt_heading[:, t])[:, None], np.sin(gt_heading[:, t])[:, None]
        d_lon = c * d[..., 0] + s * d[..., 1]
        d_lat = -s * d[..., 0] + c * d[..., 1]
        hit = ((np.abs(d_lon) <= lon * scale[:, None]) & (np.abs(d_lat) <= lat * scale[:, None])
               ).any(1)
        out[:, h] = np.where(valid[:, t], (~hit).astype(float), np.nan)
    return out


def displacement(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(minADE (S,), minFDE (S,)) of ``pred`` (S, M, T, 2) against ``gt`` (S, T, 2); the FDE at
    the last step (NaN where unobserved)."""
    d = np.linalg.norm(pred - gt[:, None], axis=-1)  # (S, M, T)
    w = valid[:, None].astype(float)
    ade = (d * w).sum(-1) / np.maximum(w.sum(-1), 1.0)
    fde = np.where(valid[:, None, -1], d[..., -1], np.nan)
    return ade.min(1), fde.min(1)


def path_heading(x: np.ndarray, y: np.ndarray, h0: float, min_step: float = 0.05
                 ) -> np.ndarray:
    """(T,) heading along a path from the current pose ``h0``: the direction of each step's
    displacement, the previous heading where it moves less than ``min_step`` m."""
    px = np.concatenate([[0.0], x])
    py = np.concatenate([[0.0], y])
    dx, dy = np.diff(px), np.diff(py)
    h = np.arctan2(dy, dx)
    moving = np.hypot(dx, dy) >= min_step
    out = np.empty_like(h)
    prev = h0
    for t in range(len(h)):  # T = 80 per sample, scored once
        prev = h[t] if moving[t] else prev
        out[t] = prev
    return out


def overlaps(scene: Scene, c: int, row: int, x: np.ndarray, y: np.ndarray, h0: float) -> bool:
    """Whether the box of track ``row`` (its size at ``c``, its recorded heading, module doc)
    placed along world-frame path ``x, y`` (steps c+1 ..) overlaps another object's recorded
    box at any step."""
    tr = scene.tracks
    steps = np.arange(c + 1, c + 1 + len(x))
    heading = np.where(tr.valid[row, steps], tr.heading[row, steps].astype(np.float64),
                       path_heading(x - tr.x[row, c], y - tr.y[row, c], h0))
    others = np.flatnonzero(np.arange(tr.num_tracks) != row)
    ok = tr.valid[others][:, steps]  # (O, T)
    if not ok.any():
        return False
    d = signed_box_distance(
        x[None], y[None], heading[None], np.float64(tr.length[row, c]), np.float64(tr.width[row, c]),
        tr.x[others][:, steps], tr.y[others][:, steps],
        tr.heading[others][:, steps].astype(np.float64),
        tr.length[others][:, steps].astype(np.float64), tr.width[others][:, steps].astype(np.float64))
    return bool((ok & (d < 0)).any())


def eval_samples(scene: Scene, history_steps: int, future_steps: int, stride: int,
                 types: np.ndarray) -> np.ndarray:
    """(S, 2) (current step, focal row) of the open-loop windows of ``scene`` (module doc)."""
    tr = scene.tracks
    out = []
    for c in range(history_steps - 1, scene.num_steps - future_steps, stride):
        rows = np.flatnonzero(np.isin(tr.type, types) & tr.valid[:, c]
                              & tr.valid[:, c + future_steps])
        out.extend((c, int(r)) for r in rows)
    return np.array(out, np.int64).reshape(-1, 2)


def _scores(scene: Scene, pairs: np.ndarray, frames: np.ndarray, pred: np.ndarray,
            best: np.ndarray, future_steps: int) -> dict[str, np.ndarray]:
    """Per-sample metrics of predictions ``pred`` (S, M, T, 2) in each sample's frame, the most
    likely mode ``best`` (S,)."""
    tr = scene.tracks
    gts, valids, heads, speeds = [], [], [], []
    for (c, r), fr in zip(pairs, frames):
        g, m = log_future(scene, int(c), np.array([r]), fr, future_steps)
        gts.append(g[0])
        valids.append(m[0])
        j = np.minimum(np.arange(c + 1, c + 1 + future_steps), tr.num_steps - 1)
        heads.append(tr.heading[r, j].astype(np.float64) - fr[2])
        speeds.append(float(np.hypot(tr.vx[r, c], tr.vy[r, c])))
    gt, valid = np.stack(gts).astype(np.float64), np.stack(valids)
    ade, fde = displacement(pred, gt, valid)
    miss = misses(pred, gt, np.stack(heads), valid, np.array(speeds))
    ov = np.empty(len(pairs))
    for k, ((c, r), fr) in enumerate(zip(pairs, frames)):
        wx, wy = Frame(*fr).to_world(pred[k, best[k], :, 0], pred[k, best[k], :, 1])
        ov[k] = overlaps(scene, int(c), int(r), wx, wy, float(fr[2]))
    with np.errstate(all="ignore"):
        mr = np.nanmean(miss, axis=1)
    return {"min_ade": ade, "min_fde": fde, "miss_rate_3s": miss[:, 0],
            "miss_rate_5s": miss[:, 1], "miss_rate_8s": miss[:, 2], "miss_rate": mr,
            "overlap_rate": ov}


@torch.no_grad()
def evaluate_openloop(model, cfg, scene_files: list[str | Path], batch_size: int = 64,
                      max_windows: int | None = None) -> dict:
    """Open-loop metrics (module doc) of ``model`` (a :class:`~magail_sumo.models.gameformer.GameFormer`
    in eval mode, config ``cfg``: a TrainConfig) on every scene of ``scene_files``.

    :param max_windows: at most this many current steps per scene (evenly spread), to bound
        the time.
    :returns: ``{"levels": {"level0": {metric: mean}, ...}, "constvel": {...}, "samples": S,
        "scenes": [scenario ids], "per_scene": [...]}``.
    """
    g = cfg.gameformer
    f = g.model.future_steps
    levels = g.model.levels + 1
    per: dict[str, list[np.ndarray]] = {}
    scenes, per_scene = [], []
    for path in scene_files:
        for scene in iter_scenes(path):
            pairs = eval_samples(scene, g.history_steps, f, g.eval_stride,
                                 focal_types(g.focal_types))
            if max_windows is not None and len(pairs):
                cs = np.unique(pairs[:, 0])
                keep = cs[np.unique(np.linspace(0, len(cs) - 1, max_windows).round().astype(int))]
                pairs = pairs[np.isin(pairs[:, 0], keep)]
            if not len(pairs):
                continue
            scenes.append(scene.scenario_id)
            chunks = map_chunks(scene, g.map_points, g.map_spacing)
            preds = [[] for _ in range(levels)]
            bests = [[] for _ in range(levels)]
            frames = []
            hist_of: dict[int, object] = {}
            for k in range(0, len(pairs), batch_size):
                samples = []
                for c, r in pairs[k:k + batch_size]:
                    if c not in hist_of:
                        hist_of = {c: log_history(scene, int(c), g.history_steps)}
                    samples.append(build_sample(hist_of[c], int(r), chunks, g.max_agents,
                                                g.map_elements))
                b = collate(samples)
                frames.extend(s["frame"] for s in samples)
                outs = model(b["agents"].to(cfg.device), b["agent_mask"].to(cfg.device),
                             b["map"].to(cfg.device), b["map_mask"].to(cfg.device))
                for lv, (traj, score) in enumerate(outs):
                    preds[lv].append(traj[:, 0, :, :, :2].double().cpu().numpy())
                    bests[lv].append(score[:, 0].argmax(-1).cpu().numpy())
            frames_a = np.stack(frames)
            row = {"scenario_id": scene.scenario_id, "samples": int(len(pairs))}
            for lv in range(levels):
                sc = _scores(scene, pairs, frames_a, np.concatenate(preds[lv]),
                             np.concatenate(bests[lv]), f)
                for m, v in sc.items():
                    per.setdefault(f"level{lv}/{m}", []).append(v)
                row[f"level{lv}_min_ade"] = float(np.mean(sc["min_ade"]))
            cv = constant_velocity(scene, pairs, frames_a, f)
            for m, v in _scores(scene, pairs, frames_a, cv, np.zeros(len(pairs), int), f).items():
                per.setdefault(f"constvel/{m}", []).append(v)
            per_scene.append(row)

    def means(prefix: str) -> dict[str, float]:
        out = {}
        for m in METRICS:
            v = np.concatenate(per.get(f"{prefix}/{m}", [np.array([])]))
            v = v[np.isfinite(v)]
            out[m] = float(v.mean()) if len(v) else float("nan")
        return out

    n = int(sum(len(v) for v in per.get("constvel/min_ade", [])))
    return {"levels": {f"level{lv}": means(f"level{lv}") for lv in range(levels)},
            "constvel": means("constvel"), "samples": n, "scenes": scenes,
            "per_scene": per_scene}


def constant_velocity(scene: Scene, pairs: np.ndarray, frames: np.ndarray, steps: int
                      ) -> np.ndarray:
    """(S, 1, T, 2) constant-velocity predictions in each sample's frame."""
    tr = scene.tracks
    c, r = pairs[:, 0], pairs[:, 1]
    vx, vy = tr.vx[r, c].astype(np.float64), tr.vy[r, c].astype(np.float64)
    h = frames[:, 2]
    lvx = np.cos(h) * vx + np.sin(h) * vy
    lvy = -np.sin(h) * vx + np.cos(h) * vy
    t = np.arange(1, steps + 1) * 0.1
    return np.stack([lvx[:, None] * t, lvy[:, None] * t], -1)[:, None]
