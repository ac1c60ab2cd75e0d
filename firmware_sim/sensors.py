"""Forward physics of the simulated sensors: force → capacitance (pF).

The grid uses table 1 of the 8x8 array paper (per-taxel C0 and sensitivity)
with the paper's linear response over its measured 0–10 N range. The quad
uses the empirical fits of the carbon black/PDMS paper, eqs (34) and (35)
without their constant offsets, each held flat past its turning point
(19.06 N normal, 9.625 N tangential) where the fit stops being monotone.
The quad's C0 is not given by the paper: ε0·εr·S/d with S = 10×10 mm²,
d = 2 mm and an assumed εr = 5 gives about 2.2 pF per electrode.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.calibration import (
    QUAD_NORMAL_CURVATURE_PER_N2,
    QUAD_NORMAL_SLOPE_PER_N,
    QUAD_SHEAR_CURVATURE_PER_N2,
    QUAD_SHEAR_SLOPE_PER_N,
    grid_calibration,
)

GRID_PITCH_MM = 4.0
QUAD_C0_PF = (2.21, 2.18, 2.24, 2.20)
QUAD_SIGN_X = np.array([-1.0, 1.0, -1.0, 1.0])  # C12, C22 on the +X side
QUAD_SIGN_Y = np.array([-1.0, -1.0, 1.0, 1.0])  # C21, C22 on the +Y side


def _turning_point(slope: float, curvature: float) -> float:
    return -slope / (2.0 * curvature)


def quad_normal_response(force_N: np.ndarray | float) -> np.ndarray:
    """ΔC/C0 of every electrode under normal force, fit (34) minus offset."""
    f = np.clip(force_N, 0.0, _turning_point(QUAD_NORMAL_SLOPE_PER_N, QUAD_NORMAL_CURVATURE_PER_N2))
    return QUAD_NORMAL_SLOPE_PER_N * f + QUAD_NORMAL_CURVATURE_PER_N2 * f * f


def quad_shear_response(force_N: np.ndarray | float) -> np.ndarray:
    """Signed ΔC/C0 of the electrodes on the loaded side, fit (35) minus offset."""
    magnitude = np.minimum(np.abs(force_N), _turning_point(QUAD_SHEAR_SLOPE_PER_N, QUAD_SHEAR_CURVATURE_PER_N2))
    return np.sign(force_N) * (QUAD_SHEAR_SLOPE_PER_N * magnitude + QUAD_SHEAR_CURVATURE_PER_N2 * magnitude**2)


@dataclass
class SimGrid:
    id: int
    rows: int = 8
    cols: int = 8
    kind: str = field(default="grid", init=False)

    def __post_init__(self) -> None:
        calibration = grid_calibration(self.rows, self.cols)
        self.c0_pF = np.array(calibration.c0_pF)
        self.sensitivity_per_N = np.array(calibration.sensitivity_per_N)

    @property
    def channels(self) -> int:
        return self.rows * self.cols

    def taxel_centres_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) of every taxel centre, shape (rows*cols,) each, origin at the
        array centre, x along columns, y along rows."""
        r, c = np.divmod(np.arange(self.channels), self.cols)
        return (c - (self.cols - 1) / 2) * GRID_PITCH_MM, (r - (self.rows - 1) / 2) * GRID_PITCH_MM

    def capacitance(self, forces_N: np.ndarray) -> np.ndarray:
        """(rows*cols,) normal forces → (rows*cols,) capacitances in pF."""
        return self.c0_pF * (1.0 + self.sensitivity_per_N * forces_N)

    def info(self) -> dict:
        return {"id": self.id, "kind": "grid", "rows": self.rows, "cols": self.cols}


@dataclass
class SimQuad:
    id: int
    c0_pF: tuple[float, float, float, float] = QUAD_C0_PF
    kind: str = field(default="quad", init=False)
    channels: int = field(default=4, init=False)

    def capacitance(self, fxyz_N: np.ndarray) -> np.ndarray:
        """(Fx, Fy, Fz) → (4,) capacitances C11, C12, C21, C22 in pF."""
        fx, fy, fz = fxyz_N
        relative = quad_normal_response(fz) + QUAD_SIGN_X * quad_shear_response(fx) + QUAD_SIGN_Y * quad_shear_response(fy)
        return np.asarray(self.c0_pF) * (1.0 + relative)

    def info(self) -> dict:
        return {"id": self.id, "kind": "quad"}
