"""Scenes: ground-truth loads over time for every simulated sensor.

Every scene starts with ``QUIET_S`` seconds without load so that the
service's auto-tare sees a free sensor. A scene maps time (s since the board
started) to the truth of one sensor: per-taxel normal force (rows*cols,) in N
for a grid, (Fx, Fy, Fz) in N for a quad.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np
from scipy.special import erf

from .sensors import GRID_PITCH_MM, SimGrid, SimQuad

QUIET_S = 1.0
PRESS_TAXEL = (4, 4)  # row, col (1-based), the taxel of the paper's crosstalk test
PRESS_PEAK_N = 5.0
PRESS_PERIOD_S = 2.0
SLIDE_FORCE_N = 4.0
SLIDE_SIGMA_MM = 1.5
SLIDE_RADIUS_MM = 9.0
SLIDE_PERIOD_S = 4.0
SHEAR_NORMAL_N = 8.0
SHEAR_TANGENTIAL_N = 3.0
SHEAR_PERIOD_S = 2.0


def _envelope(t: float) -> float:
    """0 during the quiet start, then a 0.5 s smooth ramp to 1."""
    x = min(max((t - QUIET_S) / 0.5, 0.0), 1.0)
    return 0.5 - 0.5 * math.cos(math.pi * x)


def gaussian_contact(grid: SimGrid, total_N: float, x_mm: float, y_mm: float, sigma_mm: float) -> np.ndarray:
    """Share of a Gaussian contact's force collected by each taxel cell.

    Each taxel's bump carries the load falling on its pitch×pitch cell; the
    Gaussian is integrated exactly over each cell (a product of erfs).
    Returns (rows*cols,) forces in N.
    """
    xc, yc = grid.taxel_centres_mm()
    half = GRID_PITCH_MM / 2
    scale = sigma_mm * math.sqrt(2.0)
    fx = 0.5 * (erf((xc + half - x_mm) / scale) - erf((xc - half - x_mm) / scale))
    fy = 0.5 * (erf((yc + half - y_mm) / scale) - erf((yc - half - y_mm) / scale))
    return total_N * fx * fy


def _idle(sensor, t):
    return np.zeros(sensor.channels if sensor.kind == "grid" else 3)


def _press(sensor, t):
    truth = _idle(sensor, t)
    if sensor.kind == "grid" and t >= QUIET_S:
        phase = ((t - QUIET_S) % PRESS_PERIOD_S) / PRESS_PERIOD_S
        row, col = PRESS_TAXEL
        truth[(min(row, sensor.rows) - 1) * sensor.cols + min(col, sensor.cols) - 1] = (
            PRESS_PEAK_N * 0.5 * (1.0 - math.cos(2.0 * math.pi * phase))
        )
    return truth


SLOW_PRESS_N = 3.0
SLOW_PRESS_RAMP_S = 8.0


def _slow_press(sensor, t):
    """A press on one taxel that creeps up over 8 s and holds: what a drift
    tracker must not mistake for drift."""
    truth = _idle(sensor, t)
    if sensor.kind == "grid":
        row, col = PRESS_TAXEL
        share = min(max((t - QUIET_S) / SLOW_PRESS_RAMP_S, 0.0), 1.0)
        truth[(min(row, sensor.rows) - 1) * sensor.cols + min(col, sensor.cols) - 1] = SLOW_PRESS_N * share
    return truth


def _two_contacts(sensor, t):
    """Two presses far apart at once (rows 2 and 7), for contact counting."""
    if sensor.kind != "grid":
        return _idle(sensor, t)
    env = _envelope(t)
    x, _ = sensor.taxel_centres_mm()
    return (gaussian_contact(sensor, 3.0 * env, x[9], -10.0, 1.0) + gaussian_contact(sensor, 2.0 * env, x[14], 10.0, 1.0))


def _slide(sensor, t):
    if sensor.kind != "grid":
        return _idle(sensor, t)
    angle = 2.0 * math.pi * max(t - QUIET_S, 0.0) / SLIDE_PERIOD_S
    return gaussian_contact(
        sensor, SLIDE_FORCE_N * _envelope(t), SLIDE_RADIUS_MM * math.cos(angle), SLIDE_RADIUS_MM * math.sin(angle), SLIDE_SIGMA_MM
    )


def _shear(sensor, t):
    if sensor.kind != "quad":
        return _idle(sensor, t)
    env = _envelope(t)
    angle = 2.0 * math.pi * max(t - QUIET_S, 0.0) / SHEAR_PERIOD_S
    return np.array(
        [SHEAR_TANGENTIAL_N * env * math.cos(angle), SHEAR_TANGENTIAL_N * env * math.sin(angle), SHEAR_NORMAL_N * env]
    )


def _demo(sensor, t):
    return _slide(sensor, t) if sensor.kind == "grid" else _shear(sensor, t)


Scene = Callable[[SimGrid | SimQuad, float], np.ndarray]

SCENES: dict[str, Scene] = {
    "idle": _idle,
    "press": _press,
    "slow_press": _slow_press,
    "two_contacts": _two_contacts,
    "slide": _slide,
    "shear": _shear,
    "demo": _demo,
}


def get_scene(name: str | Scene) -> Scene:
    """A scene by name, or ``name`` itself when it is already a scene (a callable)."""
    if callable(name):
        return name
    try:
        return SCENES[name]
    except KeyError:
        raise ValueError(f"unknown scene {name!r}; known scenes: {', '.join(SCENES)}") from None
