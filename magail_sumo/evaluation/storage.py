"""What evaluation writes and reads: rollouts as Parquet (one long table per method and scene),
their SUMO FCD replays, and the run's ``manifest.json``.

``out/rollouts/<method>/<scenario_id>.parquet`` (:func:`rollouts_path`, :func:`to_frame`,
:func:`write_parquet`, :func:`read_rollouts`); ``out/fcd/<method>/<scenario_id>/`` (:func:`
write_rollout_fcd`); ``out/manifest.json`` (:func:`write_manifest`, :func:`read_manifest`).
Every file is written atomically.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from converters.sumo.bundle import BundleLayout
from magail_sumo.inputs import InputFileError, read_json, regular_file
from magail_sumo.config import environment_versions
from magail_sumo.evaluation.protocol import DT, EvaluationError
from magail_sumo.evaluation.submission import ScenarioRollouts
from magail_sumo.outputs import atomic_path, inside, safe_name, write_text
from magail_sumo.scene import Scene
from magail_sumo.sim.fcd import SHAPES, FcdRecorder, write_replay

COLUMNS = ("scenario_id", "method", "rollout", "object_id", "step", "x", "y", "z", "heading",
           "valid")


# ---------------------------------------------------------------------------------- Parquet
def to_frame(scene: Scene, ro: ScenarioRollouts, method: str):
    """Long table (pandas) of the rollouts with the recorded history: one row per rollout,
    object and log step ``0..current + T``; ``valid`` is the log's validity for history steps
    (and for ``logreplay``), else True."""
    import pandas as pd

    tr = scene.tracks
    cur = scene.current_time_index
    R, A, T = ro.shape
    rows = np.array([int(np.flatnonzero(tr.id == i)[0]) for i in ro.object_id])
    hist = slice(0, cur + 1)

    def full(log: np.ndarray, sim: np.ndarray) -> np.ndarray:
        h = np.broadcast_to(log[rows, hist].astype(np.float32)[None], (R, A, cur + 1))
        return np.concatenate([h, sim.astype(np.float32)], axis=2)

    x, y, z, hd = (full(getattr(tr, n), getattr(ro, m)) for n, m in
                   (("x", "x"), ("y", "y"), ("z", "z"), ("heading", "heading")))
    fut_valid = (tr.valid[rows, cur + 1:cur + 1 + T] if method == "logreplay"
                 else np.ones((A, T), bool))
    valid = np.broadcast_to(np.concatenate([tr.valid[rows, hist], fut_valid], 1)[None],
                            x.shape)
    n, S = x.size, cur + 1 + T
    one = np.zeros(n, np.int8)  # the codes of a one-category column
    return pd.DataFrame({
        "scenario_id": pd.Categorical.from_codes(one, [ro.scenario_id]),
        "method": pd.Categorical.from_codes(one, [method]),
        "rollout": np.repeat(np.arange(R, dtype=np.int32), A * S),
        "object_id": np.tile(np.repeat(np.asarray(ro.object_id, np.int64), S), R),
        "step": np.tile(np.arange(S, dtype=np.int32), R * A),
        "x": x.ravel(), "y": y.ravel(), "z": z.ravel(), "heading": hd.ravel(),
        "valid": valid.ravel(),
    })


def rollouts_path(out: str | Path, method: str, scenario_id: str) -> Path:
    """``out/rollouts/<method>/<scenario_id>.parquet``, both names through
    :func:`~magail_sumo.outputs.safe_name` (unchanged for the built-in methods and real WOMD
    ids), refused (:class:`~magail_sumo.outputs.OutputError`) unless inside ``out``."""
    return inside(out, "rollouts", safe_name(method), f"{safe_name(scenario_id)}.parquet")


def write_rollout_fcd(out: str | Path, scene: Scene, ro: ScenarioRollouts, method: str,
                      bundle: Path, rollouts: int) -> list[Path]:
    """SUMO FCD of the first ``rollouts`` rollouts, each with a ``.sumocfg`` replaying it on the
    scene's converted network in ``sumo-gui`` (:mod:`magail_sumo.sim.fcd`):
    ``out/fcd/<method>/<scenario_id>/rollout<r>.fcd.xml`` (names through
    :func:`~magail_sumo.outputs.safe_name`). The recorded history (log steps ``0..current``,
    where valid) is followed by the simulated steps; times are ``step * 0.1`` s. Returns the
    ``.sumocfg`` paths."""
    tr = scene.tracks
    cur = scene.current_time_index
    r_n, a_n, t_n = ro.shape
    row_of = {int(i): k for k, i in enumerate(tr.id.tolist())}
    rows = np.array([row_of[int(i)] for i in ro.object_id], np.int64)
    hist = slice(0, cur + 1)
    valid = np.concatenate([tr.valid[rows, hist], np.ones((a_n, t_n), bool)], axis=1)
    size = {}
    for name in ("length", "width"):
        v = np.where(tr.valid[rows], getattr(tr, name)[rows], np.nan)
        size[name] = np.nan_to_num(np.nanmedian(v, axis=1), nan=1.0)  # valid at current
    shape = [SHAPES.get(int(t), "passenger") for t in tr.type[rows]]

    files = BundleLayout.of(bundle, scene.scenario_id)
    name, net, tll = files.name, files.net, files.signals
    times = np.arange(cur + 1 + t_n) * DT
    written = []
    for r in range(min(rollouts, r_n)):
        rec = FcdRecorder(DT)
        x, y, hd = (np.concatenate([getattr(tr, n)[rows, hist].astype(np.float64),
                                    getattr(ro, m)[r].astype(np.float64)], axis=1)
                    for n, m in (("x", "x"), ("y", "y"), ("heading", "heading")))
        rec.add_tracks(times, ro.object_id, x, y, hd, valid, size["length"], size["width"],
                       "agent", shape)
        path = inside(out, "fcd", safe_name(method), name, f"rollout{r:03d}.fcd.xml")
        written.append(write_replay(rec, path, net, [tll] if tll.is_file() else []).sumocfg)
    return written


def write_parquet(path: str | Path, frame) -> None:
    """Write ``frame`` to ``path`` atomically (a temporary file renamed into place)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        frame.to_parquet(tmp, index=False)


def read_rollouts(path: str | Path, scene: Scene) -> ScenarioRollouts:
    """Simulated steps (after the scene's current step) of a rollouts Parquet file.

    :raises EvaluationError: unreadable file, missing columns, another scene, or a ragged
        table (agents without every rollout and step), naming the file / scene / agent.
    """
    return read_rollouts_valid(path, scene)[0]


def read_rollouts_valid(path: str | Path, scene: Scene
                        ) -> tuple[ScenarioRollouts, np.ndarray | None]:
    """:func:`read_rollouts` and the file's (R, A, T) ``valid`` column over the simulated
    steps in the same order (None when every state is valid or the column cannot be read as
    booleans; a missing value is not valid), from one read of the file (pyarrow's columns as
    arrays; rows sorted by rollout, object and step)."""
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    path = Path(path)
    try:
        regular_file(path, "a rollouts Parquet file")  # a FIFO would block the reader
        table = pq.read_table(path)
    except InputFileError as exc:
        raise EvaluationError(str(exc)) from None
    except Exception as exc:
        raise EvaluationError(f"{path}: unreadable Parquet ({type(exc).__name__})") from None
    missing = [c for c in COLUMNS if c not in table.column_names]
    if missing:
        raise EvaluationError(f"{path}: missing column(s) {', '.join(missing)}")
    try:
        sids = pc.unique(table.column("scenario_id").cast("string")).to_pylist()
    except Exception as exc:
        raise EvaluationError(f"{path}: unreadable column scenario_id ({type(exc).__name__})"
                              ) from None
    sid = scene.scenario_id
    if len(sids) != 1 or sids[0] != sid:
        raise EvaluationError(f"{path}: holds scenario(s) {', '.join(map(str, sids[:3]))}, "
                              f"expected {sid}")
    col = lambda name: table.column(name).to_numpy()  # noqa: E731
    step = col("step")
    fut = np.flatnonzero(step > scene.current_time_index)
    rollout, object_id = col("rollout")[fut], col("object_id")[fut]
    order = fut[np.lexsort((step[fut], object_id, rollout))]
    ids, counts = np.unique(object_id, return_counts=True)
    R, A = len(np.unique(rollout)), len(ids)
    if A == 0:
        raise EvaluationError(f"scenario {sid}: {path.name} has no simulated steps")
    T, rem = divmod(len(fut), R * A)
    bad = np.flatnonzero(counts != counts.max())
    if rem or len(bad):
        k = int(bad[0]) if len(bad) else 0
        raise EvaluationError(f"scenario {sid}: agent {int(ids[k])} has {int(counts[k])} "
                              f"rows in {path.name}, others {int(counts.max())} "
                              "(every agent needs every rollout and step)")
    arr = {c: np.asarray(col(c)[order], np.float32).reshape(R, A, T)
           for c in ("x", "y", "z", "heading")}
    ro = ScenarioRollouts(sid, ids.astype(np.int64), arr["x"], arr["y"], arr["z"],
                          arr["heading"])
    try:  # a missing value: not valid
        v = np.asarray(pc.fill_null(table.column("valid"), False).to_numpy(), bool)[order]
        valid = None if v.all() else v.reshape(ro.shape)
    except Exception:  # noqa: BLE001 - the states themselves are read: every one is drawn
        valid = None
    return ro, valid


# --------------------------------------------------------------------------------- manifest
def versions() -> dict[str, str]:
    out = dict(environment_versions())
    for pkg in ("pandas", "pyarrow", "libsumo", "sumolib"):
        try:
            from importlib import metadata

            out[pkg] = metadata.version(pkg)
        except Exception:
            pass
    return out


def previous_manifest(out: Path) -> dict:
    """``out/manifest.json`` as a dict to merge into ({} when absent, unreadable or not an
    object; :func:`read_manifest` is the strict reader)."""
    path = out / "manifest.json"
    try:
        man = read_json(path, expected="a manifest") if path.is_file() else {}
    except InputFileError:
        man = {}
    return man if isinstance(man, dict) else {}


def write_manifest(out: Path, manifest: dict) -> None:
    """Merge ``manifest`` into ``out/manifest.json`` (methods and scenes accumulate; an
    unreadable old manifest is replaced); written atomically, refused
    (:class:`~magail_sumo.outputs.OutputError`) when it leads out of ``out``."""
    path = inside(out, "manifest.json")
    old = previous_manifest(out)
    if old and (old.get("rollouts"), old.get("seed")) != (manifest["rollouts"], manifest["seed"]):
        # another run setting: start afresh (city results, evaluation.city, do not depend on it)
        old = {"city": old["city"]} if "city" in old else {}
    scenes = {s["scenario_id"]: s for s in old.get("scenes", [])}
    scenes.update({s["scenario_id"]: s for s in manifest["scenes"]})
    methods = list(dict.fromkeys(list(old.get("methods", [])) + list(manifest["methods"])))
    fixes = {(f["scenario_id"], f["method"]): f for f in old.get("action_fixes", [])
             if isinstance(f, dict) and f.get("method") not in manifest["methods"]}
    fixes.update({(f["scenario_id"], f["method"]): f for f in manifest.get("action_fixes", [])})
    merged = {**old, **manifest, "scenes": list(scenes.values()), "methods": methods,
              "action_fixes": list(fixes.values())}
    write_text(path, json.dumps(merged, indent=2) + "\n")


def read_manifest(out: str | Path) -> dict:
    path = Path(out) / "manifest.json"
    if not path.is_file():
        raise EvaluationError(f"{path}: no manifest (run magail-sumo evaluate --out {out})")
    try:
        return read_json(path, expected="a manifest")
    except InputFileError as exc:
        raise EvaluationError(f"unreadable manifest: {exc}") from None

