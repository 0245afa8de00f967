"""Conversions between the scene frame and SUMO's vehicle conventions (arrays of vehicles).

Scene frame: box centre ``x, y`` (m) and ``yaw`` (rad, CCW from +x). SUMO: the position of a
vehicle is its front bumper centre and its angle is in degrees clockwise from north (+y):
``angle = (90 - deg(yaw)) mod 360``. Log coordinates and SUMO coordinates are the same
(networks are built without offset).
"""

from __future__ import annotations

import numpy as np


def yaw_to_sumo_angle(yaw: np.ndarray) -> np.ndarray:
    """SUMO angle in degrees [0, 360) of a scene-frame yaw in radians."""
    return np.mod(90.0 - np.degrees(yaw), 360.0)


def sumo_angle_to_yaw(angle: np.ndarray) -> np.ndarray:
    """Scene-frame yaw in radians [-pi, pi) of a SUMO angle in degrees."""
    return np.mod(np.radians(90.0 - np.asarray(angle, np.float64)) + np.pi, 2 * np.pi) - np.pi


def centre_to_front(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Front-bumper position of boxes given by centre, yaw and length."""
    half = 0.5 * np.asarray(length, np.float64)
    return x + half * np.cos(yaw), y + half * np.sin(yaw)


def front_to_centre(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Box centre of vehicles given by front-bumper position, yaw and length."""
    half = 0.5 * np.asarray(length, np.float64)
    return x - half * np.cos(yaw), y - half * np.sin(yaw)
