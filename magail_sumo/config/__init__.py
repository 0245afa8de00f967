"""Run configuration as data: typed dataclasses loaded from YAML with strict checking
(:mod:`.strict`), configs that compose (``extends:``, ``--set`` overrides: :mod:`.compose`),
and the run record (:mod:`.record`)."""

from .compose import (MAX_EXTENDS_DEPTH, MAX_EXTENDS_FILES, MAX_OVERRIDE, compose_config,
                      count_settings, load_config, merge, parse_override)
from .record import environment_versions, git_commit, record_run
from .strict import (MAX_CONFIG_BYTES, MAX_MESSAGE, ConfigError, FieldError, check,
                     check_positive, check_sizes, from_dict, is_plain_key, show, to_dict)

__all__ = ["ConfigError", "FieldError", "MAX_CONFIG_BYTES", "MAX_EXTENDS_DEPTH",
           "MAX_EXTENDS_FILES", "MAX_MESSAGE", "MAX_OVERRIDE", "check", "check_positive",
           "check_sizes", "compose_config", "count_settings", "environment_versions",
           "from_dict", "git_commit", "is_plain_key", "load_config", "merge", "parse_override",
           "record_run", "show", "to_dict"]
