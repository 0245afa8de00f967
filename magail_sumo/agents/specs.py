"""The words of a policy spec that need no policy code: the baselines evaluation runs itself, the
built-in policies and the ``guarded:`` prefix (the resolver is :mod:`magail_sumo.policies`; these
sit low so that torch-free processes, such as evaluation's baseline workers and the report's
scoring workers, can read specs)."""

from __future__ import annotations

#: methods that are no env policy: whole-trajectory models (evaluation runs them itself)
BASELINES = ("logreplay", "constvel", "sumo")
#: policies built in by name: uniform random actions; the IDM route follower
#: (:mod:`magail_sumo.agents.idm`)
BUILTIN_POLICIES = ("random", "idm")
#: ``make_policy`` spec prefix: the policy that follows, driven through the gap guard
#: (:mod:`magail_sumo.env.guard`, default settings) in evaluation
GUARDED = "guarded:"


def unguarded(spec: str) -> str:
    """``spec`` without its ``guarded:`` prefixes: the policy the gap guard drives."""
    while spec.startswith(GUARDED):
        spec = spec[len(GUARDED):]
    return spec


__all__ = ["BASELINES", "BUILTIN_POLICIES", "GUARDED", "unguarded"]
