"""A converted scene bundle: the recorded scene plus the SUMO scenario folder built from it.

The layout, its completeness check and the reader are defined once, beside the writer, in
:mod:`converters.sumo.bundle`; this module re-exports the reader for the env's callers.
"""

from converters.sumo.bundle import BundleError, SceneBundle

__all__ = ["BundleError", "SceneBundle"]
