"""Evaluation of simulated rollouts under the WOSAC protocol.

* :mod:`.protocol`: the protocol's constants (80 simulated steps), seeds and errors;
* :mod:`.scenes`: the scenes read and prepared once (with their SUMO bundles);
* :mod:`.methods`: how each method (log replay, constant velocity, SUMO, a policy) produces a
  scene's rollouts;
* :mod:`.runner`: ``magail-sumo evaluate``'s run (:func:`~.runner.evaluate`), the SUMO methods
  batched over worker processes;
* :mod:`.storage`: the rollouts' Parquet and FCD files and the run's manifest;
* :mod:`.submission` (exposed here): WOSAC submission I/O; :mod:`.realism`: the realism
  metrics; :mod:`.traffic`: the traffic metrics; :mod:`.report`: the report;
  :mod:`.city`: policies on whole SUMO cities; :mod:`.openloop`: open-loop prediction metrics.
"""

from magail_sumo.evaluation.submission import (
    RolloutsRecord, ScenarioRollouts, SubmissionError, iter_submission, read_submission,
    validate_rollouts, write_submission,
)

__all__ = ["RolloutsRecord", "ScenarioRollouts", "SubmissionError", "iter_submission",
           "read_submission", "validate_rollouts", "write_submission"]
