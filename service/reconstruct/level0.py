"""Level-0 reconstruction: the cheapest fidelity level, linear in ΔC/C0.

Grid taxel:  F = (ΔC/C0) / s, with s the taxel's sensitivity (fraction per N,
table 1 of the 8x8 array paper) and C0 the taxel's own tared baseline. Exact
for the linear 0–10 N range the paper measured; no crosstalk or drift
handling.

Quad sensor (electrodes C11, C12, C21, C22; C12 and C22 on the +X side, C21
and C22 on the +Y side), per electrode r = ΔC/C0 against its own baseline:

    r_Z = (r11 + r12 + r21 + r22) / 4            paper 001 eq (19)
    r_X = ((r12 + r22) − (r11 + r21)) / 4        eq (30)
    r_Y = ((r21 + r22) − (r11 + r12)) / 4        eq (32)
    Fz = r_Z / 0.0343,  Fx = r_X / 0.0077,  Fy = r_Y / 0.0077

(the small-force slopes of fits (34) and (35)). Fz is positive in
compression; Fx (Fy) is positive when the +X (+Y) electrodes gain
capacitance. Normalising each electrode by its own baseline before combining
removes electrode-to-electrode C0 spread that eqs (19)/(30) would otherwise
turn into force.

All functions accept a leading batch axis.
"""
from __future__ import annotations

import numpy as np

from ..physics.paper_data import QUAD_NORMAL_SLOPE_PER_N, QUAD_SHEAR_SLOPE_PER_N, GridCalibration


def relative_change(capacitance_pF: np.ndarray, baseline_pF: np.ndarray) -> np.ndarray:
    """ΔC/C0 per channel; shape (..., channels). NaN where either is NaN."""
    return capacitance_pF / baseline_pF - 1.0


def grid_forces(capacitance_pF: np.ndarray, baseline_pF: np.ndarray, calibration: GridCalibration) -> np.ndarray:
    """Per-taxel normal force in N.

    Parameters
    ----------
    capacitance_pF : (..., rows*cols) array, NaN for no reading
    baseline_pF : (rows*cols,) array
    calibration : per-taxel sensitivity, shape (rows*cols,)

    Returns
    -------
    (..., rows*cols) array of forces in N, NaN where there is no reading.
    """
    return relative_change(capacitance_pF, baseline_pF) / calibration.sensitivity_per_N


def quad_axes(relative: np.ndarray) -> np.ndarray:
    """Electrode ΔC/C0 of shape (..., 4) → (..., 3) as (r_X, r_Y, r_Z)."""
    r11, r12, r21, r22 = np.moveaxis(relative, -1, 0)
    return np.stack(
        [((r12 + r22) - (r11 + r21)) / 4.0, ((r21 + r22) - (r11 + r12)) / 4.0, (r11 + r12 + r21 + r22) / 4.0],
        axis=-1,
    )


def quad_forces(capacitance_pF: np.ndarray, baseline_pF: np.ndarray) -> np.ndarray:
    """Quad force (Fx, Fy, Fz) in N from electrode capacitances.

    Parameters
    ----------
    capacitance_pF : (..., 4) array, order C11, C12, C21, C22
    baseline_pF : (4,) array

    Returns
    -------
    (..., 3) array (Fx, Fy, Fz) in N; all three NaN if any electrode has no
    reading, since each axis combines all four.
    """
    axes = quad_axes(relative_change(capacitance_pF, baseline_pF))
    return axes / np.array([QUAD_SHEAR_SLOPE_PER_N, QUAD_SHEAR_SLOPE_PER_N, QUAD_NORMAL_SLOPE_PER_N])
