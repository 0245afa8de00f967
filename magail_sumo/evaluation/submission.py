"""Sim-agents submissions (WOSAC ``SimAgentsChallengeSubmission`` protos) as arrays.

A scenario's rollouts are ``(R, A, T)`` float32 arrays of box-centre positions (metres, the
scene's own frame) and headings (radians CCW from +x) for the ``A`` simulated objects over the
``T`` simulated steps after the scene's current step (R = 32, T = 80 in the challenge). Reading
never stops at a bad scenario: :func:`iter_submission` yields one record per scenario with
either the arrays or a one-line :class:`SubmissionError`, and :func:`validate_rollouts` checks
them against the scene they simulate.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from os import PathLike
from typing import Iterable, Iterator, Sequence

import numpy as np

from converters.womd.protos import sim_agents_submission_pb2 as pb
from magail_sumo.errors import MagailSumoError
from magail_sumo.inputs import GiB, InputFileError, read_bytes
from magail_sumo.outputs import write_bytes
from magail_sumo.scene import Scene
from magail_sumo.scene.validation import MAX_COORDINATE


#: the largest submission file read (protobuf's own message limit)
SUBMISSION_LIMIT = 2 * GiB


class SubmissionError(MagailSumoError):
    """A submission, or one scenario of it, cannot be scored.

    :param scenario_id: the scenario ("" when the whole file is bad).
    :param problem: what is wrong (names the rollout / agent / step where it applies).
    """

    def __init__(self, scenario_id: str, problem: str) -> None:
        self.scenario_id = scenario_id
        self.problem = problem
        super().__init__(f"scenario {scenario_id}: {problem}" if scenario_id else problem)


@dataclass(frozen=True, eq=False)
class ScenarioRollouts:
    """Simulated futures of one scenario.

    :param scenario_id: dataset scenario id.
    :param object_id: (A,) int64 track ids of the simulated objects.
    :param x, y, z: (R, A, T) float32 box centre, metres, scene frame.
    :param heading: (R, A, T) float32 yaw, radians CCW from +x.
    """

    scenario_id: str
    object_id: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    heading: np.ndarray

    @property
    def shape(self) -> tuple[int, int, int]:
        """(rollouts, objects, steps)."""
        return self.x.shape  # type: ignore[return-value]


@dataclass(frozen=True)
class RolloutsRecord:
    """One scenario of a submission file: ``rollouts`` or ``error``."""

    index: int
    scenario_id: str
    rollouts: ScenarioRollouts | None = None
    error: SubmissionError | None = None


_COORDS = ("center_x", "center_y", "center_z", "heading")


def rollouts_from_proto(msg: pb.ScenarioRollouts) -> ScenarioRollouts:
    """Arrays of one ``ScenarioRollouts`` message.

    :raises SubmissionError: no scenario id or joint scenes, differing or repeated agent sets
        between joint scenes, or trajectories of differing lengths.
    """
    sid = msg.scenario_id
    if not msg.HasField("scenario_id"):
        raise SubmissionError("", "missing scenario_id")
    if not msg.joint_scenes:
        raise SubmissionError(sid, "no joint scenes (rollouts)")
    first = msg.joint_scenes[0].simulated_trajectories
    ids = [t.object_id for t in first]
    if not ids:
        raise SubmissionError(sid, "rollout 0 has no simulated trajectories")
    dup = [i for i, n in Counter(ids).items() if n > 1]
    if dup:
        raise SubmissionError(sid, f"rollout 0: agent {dup[0]} appears {ids.count(dup[0])} times")
    # the step count is the most common length of rollout 0's coordinate fields, so that the
    # one short field is named (not its correct siblings)
    steps = Counter(len(getattr(t, name)) for t in first for name in _COORDS).most_common(1)[0][0]
    order = {i: k for k, i in enumerate(ids)}
    R, A = len(msg.joint_scenes), len(ids)
    out = np.empty((4, R, A, steps), np.float32)
    for r, js in enumerate(msg.joint_scenes):
        trajs = js.simulated_trajectories
        got = [t.object_id for t in trajs]
        if Counter(got) != Counter(ids):
            extra = sorted(set(got) - set(ids))
            missing = sorted(set(ids) - set(got))
            dup = [i for i, n in Counter(got).items() if n > 1]
            what = (f"agent {extra[0]} not in rollout 0" if extra else
                    f"agent {missing[0]} missing" if missing else f"agent {dup[0]} repeated")
            raise SubmissionError(sid, f"rollout {r}: {what} (agent sets must match)")
        for t in trajs:
            a = order[t.object_id]
            for c, name in enumerate(_COORDS):
                vals = getattr(t, name)
                if len(vals) != steps:
                    raise SubmissionError(sid, f"rollout {r} agent {t.object_id}: {len(vals)} "
                                               f"steps of {name}, expected {steps}")
                out[c, r, a] = vals
    return ScenarioRollouts(sid, np.asarray(ids, np.int64), *out)


def rollouts_to_proto(ro: ScenarioRollouts) -> pb.ScenarioRollouts:
    """The ``ScenarioRollouts`` message of arrays (positions and headings only)."""
    msg = pb.ScenarioRollouts(scenario_id=ro.scenario_id)
    x, y, z, h = (np.asarray(a, np.float32) for a in (ro.x, ro.y, ro.z, ro.heading))
    for r in range(x.shape[0]):
        js = msg.joint_scenes.add()
        for a, oid in enumerate(ro.object_id.tolist()):
            js.simulated_trajectories.add(center_x=x[r, a], center_y=y[r, a], center_z=z[r, a],
                                          heading=h[r, a], object_id=int(oid))
    return msg


def iter_submission(paths: str | PathLike | Iterable[str | PathLike]) -> Iterator[RolloutsRecord]:
    """One record per scenario of submission files (or shards), bad ones included.

    :raises SubmissionError: a file that cannot be read or parsed at all.
    """
    if isinstance(paths, (str, PathLike)):
        paths = [paths]
    index = 0
    for path in paths:
        try:
            # a regular file of at most 2 GiB (protobuf's own limit)
            data = read_bytes(path, SUBMISSION_LIMIT, "a submission file")
        except InputFileError as exc:
            raise SubmissionError("", str(exc)) from None
        try:
            sub = pb.SimAgentsChallengeSubmission.FromString(data)
        except Exception as exc:  # DecodeError has no stable public class
            raise SubmissionError("", f"{path}: not a readable SimAgentsChallengeSubmission "
                                      f"({type(exc).__name__}: {exc})") from None
        for msg in sub.scenario_rollouts:
            try:
                yield RolloutsRecord(index, msg.scenario_id, rollouts=rollouts_from_proto(msg))
            except SubmissionError as exc:
                yield RolloutsRecord(index, msg.scenario_id, error=exc)
            index += 1


def read_submission(paths: str | PathLike | Iterable[str | PathLike]) -> list[ScenarioRollouts]:
    """All scenarios' rollouts; raises the first :class:`SubmissionError`."""
    out = []
    for rec in iter_submission(paths):
        if rec.error is not None:
            raise rec.error
        out.append(rec.rollouts)
    return out  # type: ignore[return-value]


def write_submission(path: str | PathLike, rollouts: Sequence[ScenarioRollouts], *,
                     account_name: str = "", method_name: str = "magail_sumo",
                     description: str = "", authors: Sequence[str] = (),
                     affiliation: str = "", method_link: str = "",
                     num_model_parameters: str = "0", uses_lidar_data: bool = False,
                     uses_camera_data: bool = False,
                     uses_public_model_pretraining: bool = False) -> None:
    """Write a ``SimAgentsChallengeSubmission`` file (name it ``*.binproto``)."""
    sub = pb.SimAgentsChallengeSubmission(
        submission_type=pb.SimAgentsChallengeSubmission.SIM_AGENTS_SUBMISSION,
        account_name=account_name, unique_method_name=method_name, authors=list(authors),
        affiliation=affiliation, description=description, method_link=method_link,
        uses_lidar_data=uses_lidar_data, uses_camera_data=uses_camera_data,
        uses_public_model_pretraining=uses_public_model_pretraining,
        num_model_parameters=num_model_parameters,
        acknowledge_complies_with_closed_loop_requirement=True)
    sub.scenario_rollouts.extend(rollouts_to_proto(r) for r in rollouts)

    write_bytes(path, sub.SerializeToString())  # atomic: the old file or the whole new one


def sim_agent_ids(scene: Scene) -> np.ndarray:
    """(A,) ids of the objects to simulate: tracks valid at the current step, in track order."""
    tr = scene.tracks
    return tr.id[tr.valid[:, scene.current_time_index]].astype(np.int64)


def validate_rollouts(ro: ScenarioRollouts, scene: Scene, n_rollouts: int = 32,
                      n_steps: int = 80) -> None:
    """Check rollouts against the scene they simulate (official challenge rules).

    :raises SubmissionError: wrong scenario, rollout count, agent set or step count, or
        non-finite positions / headings (naming the first rollout, agent and step).
    """
    sid = ro.scenario_id
    if sid != scene.scenario_id:
        raise SubmissionError(sid, f"rollouts given for scene {scene.scenario_id}")
    R, A, T = ro.shape
    if R != n_rollouts:
        raise SubmissionError(sid, f"{R} rollouts, expected {n_rollouts}")
    want = sim_agent_ids(scene)
    missing = np.setdiff1d(want, ro.object_id)
    extra = np.setdiff1d(ro.object_id, want)
    if len(missing) or len(extra):
        parts = []
        if len(missing):
            parts.append(f"missing agent(s) {', '.join(map(str, missing[:5]))}"
                         + (" …" if len(missing) > 5 else ""))
        if len(extra):
            parts.append(f"agent(s) {', '.join(map(str, extra[:5]))} not valid at step "
                         f"{scene.current_time_index}" + (" …" if len(extra) > 5 else ""))
        raise SubmissionError(sid, f"wrong agent set ({len(want)} to simulate): "
                                   + "; ".join(parts))
    if T != n_steps:
        raise SubmissionError(sid, f"agent {int(ro.object_id[0])}: {T} simulated steps, "
                                   f"expected {n_steps}")
    for name in ("x", "y", "z", "heading"):
        bad = ~np.isfinite(getattr(ro, name))
        if bad.any():
            r, a, t = (int(i[0]) for i in np.nonzero(bad))
            raise SubmissionError(sid, f"rollout {r} agent {int(ro.object_id[a])}: non-finite "
                                       f"{name} at simulated step {t}")
    for name in ("x", "y", "z"):  # finite but huge (1e308): out of range, not "non-finite"
        arr = getattr(ro, name)
        bad = np.abs(arr) > MAX_COORDINATE
        if bad.any():
            r, a, t = (int(i[0]) for i in np.nonzero(bad))
            raise SubmissionError(sid, f"rollout {r} agent {int(ro.object_id[a])}: {name} "
                                       f"{float(arr[r, a, t]):.6g} out of range (|{name}| > "
                                       f"{MAX_COORDINATE:g} m) at simulated step {t}")
