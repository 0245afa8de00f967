"""Convert recorded scenes into SUMO scenarios: network, signal programs, routes, quality."""

from .scenario import ConversionReport, ConvertOptions, convert_scene

__all__ = ["ConversionReport", "ConvertOptions", "convert_scene"]
