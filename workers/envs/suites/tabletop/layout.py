"""Geometry of the tabletop scene, without robosuite: the task logic and the experts read it in
the driver (pre-flight checks) where importing robosuite would import MuJoCo, and so pick a GL
backend, before the worker has chosen one."""

from __future__ import annotations

import numpy as np

CUBE_HALF = 0.02
TABLE_TOP_Z = 0.8
COLORS: dict[str, tuple[float, float, float, float]] = {
    "red": (0.9, 0.1, 0.1, 1.0),
    "green": (0.1, 0.75, 0.1, 1.0),
    "blue": (0.1, 0.3, 0.95, 1.0),
    "yellow": (0.95, 0.85, 0.1, 1.0),
    "purple": (0.6, 0.15, 0.8, 1.0),
}
BIN_CENTER = np.array([0.0, 0.24])  # xy on the table
BIN_INNER_HALF = 0.095  # inner half width of the bin
BIN_WALL = (0.005, 0.025)  # wall half thickness, half height
