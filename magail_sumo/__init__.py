"""magail_sumo: SUMO co-simulation framework for multi-agent imitation learning of driving."""

__version__ = "0.1.0"
