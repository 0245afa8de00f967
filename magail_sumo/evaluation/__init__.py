"""Evaluation of simulated rollouts: submission I/O and the WOSAC realism metrics."""

from magail_sumo.evaluation.submission import (
    RolloutsRecord, ScenarioRollouts, SubmissionError, iter_submission, read_submission,
    validate_rollouts, write_submission,
)

__all__ = ["RolloutsRecord", "ScenarioRollouts", "SubmissionError", "iter_submission",
           "read_submission", "validate_rollouts", "write_submission"]
