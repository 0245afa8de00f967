"""The built-in sensor units, one module each; importing the package registers them
(:func:`magail_sumo.sensors.base.register`)."""

from . import command, destination, ego, lane, lane_line, lidar, light, seed, side

__all__ = ["command", "destination", "ego", "lane", "lane_line", "lidar", "light", "seed", "side"]
