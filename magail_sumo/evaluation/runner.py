"""``magail-sumo evaluate``'s run: every method's rollouts of every scene, the SUMO ones batched
over fresh worker processes, written as Parquet with the run's manifest.

:func:`evaluate` takes its steps in order: check the settings (:func:`method_names`), read and
prepare the scenes once (:mod:`magail_sumo.evaluation.scenes`), run the methods
(:func:`run_methods`: the in-process ones here, the others as :class:`Batch` es in fresh
processes, forked from a server that imported SUMO and the methods' code once
(:data:`WORKER_IMPORTS`): up to 32 rollouts of SUMO's car-following per process
(:func:`run_batches`), a policy's rollouts of a scene in as few batches as keep the workers
busy (:func:`batch_size`), one process per worker running its share of them in turn
(:func:`run_groups`)), write each (scene,
method)'s rollouts as soon as they are all in (:func:`write_pair`: while the workers run on,
the in-process methods' once the first worker's results are in), then the manifest
(:func:`manifest_of`) and the optional submission.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from magail_sumo.errors import MagailSumoError
from magail_sumo.evaluation.methods import Batch, needs_worker, run_batches_in_turn, simulate
from magail_sumo.evaluation.protocol import (DEFAULT_TIMEOUT_S, N_STEPS, WORKER_IMPORTS,
                                             EvaluationError, Problems, span)
from magail_sumo.evaluation.scenes import PreparedScene, read_scenes, with_bundles
from magail_sumo.evaluation.storage import (rollouts_path, to_frame, versions, write_manifest,
                                            write_parquet, write_rollout_fcd)
from magail_sumo.evaluation.submission import (ScenarioRollouts, sim_agent_ids, validate_rollouts,
                                               write_submission)
from magail_sumo.outputs import NameRegistry, claim_output_dir, inside, one_line, printable
from magail_sumo.agents.specs import BASELINES, BUILTIN_POLICIES
from magail_sumo.policies import make_policy, method_name
from magail_sumo.workers import Progress, no_progress, run_jobs


def run_batches(batches: list[Batch], workers: int, timeout_s: float | None = DEFAULT_TIMEOUT_S
                ) -> Iterator[tuple[Batch, ScenarioRollouts | None, str | None, dict[str, int]]]:
    """Run batches, each in a fresh process; yields (batch, rollouts, error line,
    fixed-up action counts) (:func:`run_groups` of one batch each)."""
    yield from run_groups([(b,) for b in batches], workers, timeout_s)


def run_groups(groups: list[tuple[Batch, ...]], workers: int,
               timeout_s: float | None = DEFAULT_TIMEOUT_S
               ) -> Iterator[tuple[Batch, ScenarioRollouts | None, str | None, dict[str, int]]]:
    """Run groups of batches, each group in one fresh process running its batches
    in turn (:func:`~magail_sumo.evaluation.methods.run_batches_in_turn`: a policy's batches
    of several scenes pay the process start and the policy's imports once); yields (batch,
    rollouts, error line, fixed-up action counts) per batch.

    A batch that raises a :class:`~magail_sumo.errors.MagailSumoError` is reported. A group
    whose worker fails otherwise (crashes, dies, raises anything else) is retried once batch
    by batch, and a failing batch of several rollouts rollout by rollout (each in its own
    process). A group running longer than ``timeout_s`` seconds per batch is killed: one batch
    is reported, several are retried one by one. No wait is unbounded
    (:func:`magail_sumo.workers.run_jobs`).
    """
    groups = [g for g in groups if g]
    if not groups:
        return
    retry: list[tuple[Batch, ...]] = []
    limit = None if timeout_s is None else (lambda g: timeout_s * len(g))
    for res in run_jobs(run_batches_in_turn, groups, workers=max(1, workers), timeout_s=limit,
                        preload=WORKER_IMPORTS):
        group: tuple[Batch, ...] = res.job
        b = group[0]
        what = f"scenario {b.scenario_id}: method {b.spec}"
        if res.ok:
            for item in res.value:
                if item[0] == "ok":
                    yield item[1], item[2], None, item[3]
                else:
                    yield item[1], None, item[2], {}
        elif len(group) > 1:  # which batch failed is unknown: each alone
            retry += [(g,) for g in group]
        elif res.kind == "error" and res.expected:
            yield b, None, res.reason, {}
        elif res.kind == "timeout":
            yield b, None, (f"{what} rollout(s) {span(b.rollouts)}: worker {res.reason} "
                            "(--timeout-s)"), {}
        elif len(b.rollouts) > 1:  # worker crash (libsumo) or bug: retry singly
            retry += [(replace(b, rollouts=(r,)),) for r in b.rollouts]
        else:
            yield b, None, f"{what} rollout {b.rollouts[0]} failed: {res.reason}", {}
    if retry:
        yield from run_groups(retry, workers, timeout_s)


def chunks(n: int, size: int) -> list[tuple[int, ...]]:
    return [tuple(range(i, min(i + size, n))) for i in range(0, n, size)]


def batch_size(n_rollouts: int, workers: int, spec: str = "sumo", n_scenes: int = 1) -> int:
    """Rollouts per worker batch: a scene's rollouts of a method are split only as far as it
    takes to give every worker a batch (a batch's process start and imports cost more than a
    small scene's rollouts). SUMO's car-following runs its rollouts one after another, up to
    :data:`SUMO_BATCH` per process (a libsumo crash costs at most that many, retried one by
    one); a policy runs them at once in the batched core
    (:func:`~magail_sumo.evaluation.methods.batched_rollouts`)."""
    size = math.ceil(n_rollouts / max(1, math.ceil(max(1, workers) / max(1, n_scenes))))
    return max(1, min(SUMO_BATCH, size) if spec in BASELINES else size)


#: most rollouts of SUMO's car-following in one worker process
SUMO_BATCH = 32


def merge(parts: list[ScenarioRollouts]) -> ScenarioRollouts:
    """Concatenate rollout batches of one scene (same agents) along the rollout axis."""
    first = parts[0]
    cat = lambda n: np.concatenate([getattr(p, n) for p in parts])  # noqa: E731
    return ScenarioRollouts(first.scenario_id, first.object_id, cat("x"), cat("y"), cat("z"),
                            cat("heading"))


# ----------------------------------------------------------------------------------- the run
@dataclass
class EvaluationResult:
    """What :func:`evaluate` wrote: (scenario, method) pairs done, and one-line errors."""

    done: list[tuple[str, str]]
    errors: list[str]


@dataclass
class MethodRuns:
    """What :func:`run_methods` produced: per (scenario, spec) the rollout parts (first rollout,
    rollouts), the pairs that failed, and a policy's fixed-up action counts."""

    parts: dict[tuple[str, str], list[tuple[int, ScenarioRollouts]]] = field(default_factory=dict)
    failed: set[tuple[str, str]] = field(default_factory=set)
    fixes: dict[tuple[str, str], dict[str, int]] = field(default_factory=dict)


def check_settings(policy: str, baselines: list[str], n_rollouts: int, fcd_rollouts: int,
                   seed: int, deterministic: bool, noise_scale: float | None) -> float | None:
    """Refuse bad counts, an unknown baseline or an unusable policy spec
    (:class:`EvaluationError` / :class:`~magail_sumo.agents.base.PolicyError`); the noise scale
    the policy samples with (None: a baseline, or a policy without one)."""
    if n_rollouts < 1:
        raise EvaluationError(f"--rollouts must be >= 1, got {n_rollouts}")
    if fcd_rollouts < 0:
        raise EvaluationError(f"--fcd-rollouts must be >= 0, got {fcd_rollouts}")
    bad = [b for b in baselines if b not in BASELINES]
    if bad:
        raise EvaluationError(f"unknown baseline {bad[0]} (known: {', '.join(BASELINES)})")
    if policy in BASELINES:
        return None
    # fail early on an unusable spec
    return getattr(make_policy(policy, seed, deterministic, noise_scale), "noise_scale", None)


def method_names(specs: list[str], policy: str, name: str | None) -> dict[str, str]:
    """Each spec's method name (:func:`method_name`; the policy's ``name`` when given), refused
    (:class:`EvaluationError`) when a name is empty, not printable or another method's, or two
    names share a file name."""
    names = {s: method_name(s) for s in specs}
    if name is not None:
        if not name.strip() or not name.isprintable() or len(name) > 100:
            raise EvaluationError(f"--name {printable(name)!r}: must be a non-empty printable "
                                  "name of at most 100 characters")
        if name in BASELINES + BUILTIN_POLICIES and name != policy:
            raise EvaluationError(f"--name {name!r}: is a built-in method's name")
        names[policy] = name
    files = NameRegistry()
    for s in specs:
        files.name(names[s])
    return names


def run_methods(scenes: dict[str, PreparedScene], specs: list[str], n_rollouts: int, seed: int,
                workers: int, timeout_s: float | None, deterministic: bool,
                noise_scale: float | None, error: Problems,
                progress: Progress = no_progress,
                complete: Callable[[MethodRuns, str, str], None] | None = None) -> MethodRuns:
    """Every method's rollouts of every scene: the in-process methods here, the SUMO ones in
    :class:`Batch` es of :func:`batch_size` rollouts (each worker gets the prepared scene);
    failures are reported (``error``) and their pairs marked failed. ``progress("rollouts",
    done, total)`` after each method of a scene or batch.

    :param complete: told ``(runs so far, scenario id, spec)`` of each pair whose rollouts are
        all in (not failed), while the workers run on: the in-process methods' pairs once the first
        worker result is in (or at the end), the workers' as their last batch comes back."""
    runs = MethodRuns()
    ready: list[tuple[str, str]] = []  # in-process pairs done before any worker result

    def done_pair(key: tuple[str, str]) -> None:
        if complete is not None and key not in runs.failed and \
                sum(ro.x.shape[0] for _, ro in runs.parts.get(key, ())) == n_rollouts:
            complete(runs, *key)

    total = len(scenes) * len(specs) * n_rollouts
    done = 0
    batches, policy_batches = [], []
    for sid, ps in scenes.items():
        for s in specs:
            if needs_worker(s):
                size = batch_size(n_rollouts, workers, s, len(scenes))
                (batches if s in BASELINES else policy_batches).extend(
                    Batch(ps.file, sid, str(ps.bundle), s, c, seed, deterministic, noise_scale,
                          ps.scene) for c in chunks(n_rollouts, size))
            else:
                try:
                    runs.parts[(sid, s)] = [(0, simulate(ps.scene, s, range(n_rollouts), seed))]
                    ready.append((sid, s))
                except Exception as exc:  # noqa: BLE001 - one scene's failure
                    error(f"scenario {sid}: method {s}: {type(exc).__name__}: {one_line(exc)}")
                done += n_rollouts
                progress("rollouts", done, total)
    # a policy's batches: one process per worker, each running its share in turn; then
    # SUMO's, one batch per process
    shares = [tuple(policy_batches[k::max(1, workers)]) for k in range(max(1, workers))]
    for b, ro, err, counts in run_groups(shares + [(b,) for b in batches], workers, timeout_s):
        done += len(b.rollouts)
        progress("rollouts", done, total)
        key = (b.scenario_id, b.spec)
        if err is not None:
            error(err)
            runs.failed.add(key)
        else:
            runs.parts.setdefault(key, []).append((b.rollouts[0], ro))
            tally = runs.fixes.setdefault(key, {})
            for k, v in counts.items():
                tally[k] = tally.get(k, 0) + v
        while ready:  # the workers are busy now: write what was computed here meanwhile
            done_pair(ready.pop(0))
        if err is None:
            done_pair(key)
    for key in ready:
        done_pair(key)
    return runs


def write_pair(out: Path, ps: PreparedScene, spec: str, name: str, runs: MethodRuns,
               n_rollouts: int, fcd_rollouts: int, error: Problems) -> ScenarioRollouts | None:
    """Merge, validate and write the rollouts of (scene ``ps``, method ``spec``) (Parquet, plus
    FCD of the first ``fcd_rollouts``); the rollouts written, or None (failed, or refused:
    reported)."""
    sid = ps.scene.scenario_id
    if (sid, spec) in runs.failed or (sid, spec) not in runs.parts:
        return None
    try:
        ro = merge([r for _, r in sorted(runs.parts[(sid, spec)], key=lambda p: p[0])])
        validate_rollouts(ro, ps.scene, n_rollouts, N_STEPS)
    except MagailSumoError as exc:
        error(f"method {name}: {' '.join(str(exc).split())}")
        return None
    except Exception as exc:  # noqa: BLE001 - one scene's failure
        error(f"scenario {printable(sid)}: method {name}: {type(exc).__name__}: "
              f"{one_line(exc)}")
        return None
    write_parquet(rollouts_path(out, name, sid), to_frame(ps.scene, ro, name))
    if fcd_rollouts and ps.bundle is not None:
        write_rollout_fcd(out, ps.scene, ro, name, Path(ps.bundle), fcd_rollouts)
    return ro


def write_rollouts(out: Path, scenes: dict[str, PreparedScene], specs: list[str],
                   names: dict[str, str], runs: MethodRuns, n_rollouts: int, fcd_rollouts: int,
                   error: Problems, written: dict[tuple[str, str], ScenarioRollouts | None]
                   | None = None) -> dict[tuple[str, str], ScenarioRollouts]:
    """:func:`write_pair` of every (scene, method) not in ``written`` (those written, or
    refused, already); every pair's rollouts written, by (scenario id, spec), in scene then
    method order."""
    written = dict(written or {})
    out_pairs: dict[tuple[str, str], ScenarioRollouts] = {}
    for sid, ps in scenes.items():
        for s in specs:
            if (sid, s) not in written:
                written[(sid, s)] = write_pair(out, ps, s, names[s], runs, n_rollouts,
                                               fcd_rollouts, error)
            if written[(sid, s)] is not None:
                out_pairs[(sid, s)] = written[(sid, s)]  # type: ignore[assignment]
    return out_pairs


def manifest_of(scenes: dict[str, PreparedScene], specs: list[str], names: dict[str, str],
                policy: str, baselines: list[str], runs: MethodRuns,
                done: list[tuple[str, str]], *, n_rollouts: int, seed: int,
                deterministic: bool, noise_scale: float | None) -> dict:
    """The run's ``manifest.json`` (:func:`~magail_sumo.evaluation.storage.write_manifest`
    merges it into an earlier one)."""
    return {
        "scenes": [{"scenario_id": sid, "file": ps.file,
                    "bundle": str(ps.bundle) if ps.bundle else None,
                    "num_steps": ps.scene.num_steps,
                    "current_time_index": ps.scene.current_time_index,
                    "agents": int(len(sim_agent_ids(ps.scene)))}
                   for sid, ps in scenes.items()],
        "methods": [names[s] for s in specs], "policy": names[policy], "policy_spec": policy,
        "baselines": [names[b] for b in baselines], "rollouts": n_rollouts, "steps": N_STEPS,
        "seed": seed, "deterministic": bool(deterministic), "noise_scale": noise_scale,
        "versions": versions(),
        # actions the policy did not give (agents coasted), gave for unknown agents, or gave
        # non-finite / outside [-1, 1] (fixed up by the env), per scene and method
        "action_fixes": [{"scenario_id": sid, "method": names[s], **c}
                         for (sid, s), c in runs.fixes.items() if (sid, names[s]) in done
                         and any(c.get(k) for k in ("missing", "unknown", "nonfinite",
                                                    "clipped"))],
    }


def evaluate(scene_files: list[str], policy: str, out: str | Path, *, n_rollouts: int = 32,
             baselines: Iterable[str] = BASELINES, seed: int = 0, workers: int = 2,
             networks: str | Path | None = None, submission: str | Path | None = None,
             timeout_s: float | None = DEFAULT_TIMEOUT_S, fcd_rollouts: int = 0,
             name: str | None = None, deterministic: bool = False,
             noise_scale: float | None = None,
             progress: Progress = no_progress) -> EvaluationResult:
    """Rollouts of ``policy`` and ``baselines`` on every scene, written as Parquet under
    ``out/rollouts/<method>/<scenario_id>.parquet`` plus ``out/manifest.json``; with
    ``fcd_rollouts`` > 0 the first that many rollouts of every scene and method also as SUMO
    FCD with a ``sumo-gui`` replay config
    (:func:`~magail_sumo.evaluation.storage.write_rollout_fcd`).

    ``out`` must be new, empty or written by magail_sumo
    (:func:`~magail_sumo.outputs.claim_output_dir`, else
    :class:`~magail_sumo.outputs.OutputError`), and what it writes there must not lead out of
    it through a symbolic link (:func:`~magail_sumo.outputs.inside`); file names come from
    :func:`~magail_sumo.evaluation.storage.rollouts_path`, the manifest and the Parquet
    ``scenario_id`` column keep the original ids, and every file is written atomically. Bad
    scenes, failed conversions and failed rollouts (any exception, a worker that dies, or one
    running past ``timeout_s`` seconds: killed) are reported (stderr, one line each) and the
    rest goes on.

    :param name: the policy's method name (default :func:`method_name` of the spec); rollouts,
        the manifest and the report use it.
    :param deterministic: a checkpoint policy acts with the tanh of its Gaussian mean (every
        rollout alike) instead of sampling its actions with the rollout seed (the default);
        recorded in the manifest.
    :param noise_scale: a sampling policy's noise scale (``tanh(mu + k·sigma·eps)``; None: the
        policy's own, 1 or a pretrained card's); the one used is recorded in the manifest.
    :param progress: told ``("rollouts", done, total)`` as rollouts finish (a CLI bar).
    :raises EvaluationError: an unknown baseline, an unusable policy spec, bad counts or a
        name that is empty, not printable or another method's.
    """
    out = Path(out)
    baselines = list(baselines)
    scale = check_settings(policy, baselines, n_rollouts, fcd_rollouts, seed, deterministic,
                           noise_scale)
    specs = list(dict.fromkeys([policy, *baselines]))
    names = method_names(specs, policy, name)
    owned = ["manifest.json", "rollouts", "networks"] + (["fcd"] if fcd_rollouts else [])
    claim_output_dir(out, "evaluate", owned)
    for name in owned:  # a symbolic link out of the folder: refused before any rollout
        inside(out, name)
    error = Problems()
    scenes = read_scenes(scene_files, error)
    if any(needs_worker(s) for s in specs) or fcd_rollouts > 0:  # FCD: the network
        scenes = with_bundles(scenes, Path(networks) if networks else None, out, timeout_s,
                              error)
    early: dict[tuple[str, str], ScenarioRollouts | None] = {}  # written while the workers ran

    def write_now(runs: MethodRuns, sid: str, spec: str) -> None:
        early[(sid, spec)] = write_pair(out, scenes[sid], spec, names[spec], runs, n_rollouts,
                                        fcd_rollouts, error)

    runs = run_methods(scenes, specs, n_rollouts, seed, workers, timeout_s, deterministic,
                       noise_scale, error, progress, complete=write_now)
    written = write_rollouts(out, scenes, specs, names, runs, n_rollouts, fcd_rollouts, error,
                             early)
    done = [(sid, names[s]) for sid, s in written]
    out.mkdir(parents=True, exist_ok=True)
    write_manifest(out, manifest_of(scenes, specs, names, policy, baselines, runs, done,
                                    n_rollouts=n_rollouts, seed=seed,
                                    deterministic=deterministic, noise_scale=scale))
    policy_ros = [ro for (_, s), ro in written.items() if s == policy]
    if submission is not None and policy_ros:
        write_submission(submission, policy_ros, method_name=names[policy],
                         description=f"magail_sumo evaluate --policy {policy}")
    return EvaluationResult(done, error.lines)
