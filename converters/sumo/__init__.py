"""Convert recorded scenes into SUMO scenarios: network, signal programs, routes, quality; the
bundle layout they are written in and its reader (:mod:`.bundle`)."""

from .bundle import BundleError, BundleLayout, SceneBundle
from .scenario import ConversionReport, ConvertOptions, convert_scene, ensure_bundle

__all__ = ["BundleError", "BundleLayout", "ConversionReport", "ConvertOptions", "SceneBundle",
           "convert_scene", "ensure_bundle"]
