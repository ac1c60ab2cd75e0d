"""Quad reconstruction: (Fx, Fy, Fz) from four electrodes, calibrated models.

Forward model of electrode ij (sx, sy = ±1 on the +X/+Y side, r = ΔC/C0):

    r_ij = n(Fz) + (sx t(Fx) + sy t(Fy)) · (1 − c · n(Fz))

n is the calibrated normal curve (default: fit (34) without its offset; the
Yeoh fit misses it by 0.37 N RMS, far above the noise, so the calibration
data itself is inverted), t the calibrated shear curve r = aF − bF² (fit
(35)), c the normal–shear interaction of paper 001 §5.3 (normal load
hinders the tangential deformation; default 0, the paper gives no figure).
The four electrodes span four orthogonal combinations: Z = mean, X and Y
(eqs 30, 32) and the redundant R = (r11 + r22 − r12 − r21)/4, which the
model says is 0. The joint least-squares solution is therefore exact in
closed form: Fz from Z first, then Fx, Fy from X, Y divided by
(1 − c·n(Fz)); |R| beyond its noise flags an electrode fault.

Out of the calibrated range (past the usable force, or a ΔC/C0 the curve
never reaches, or a negative normal change) the force is held at the range's
end and flagged, never taken from the falling branch of a fit.
"""
from __future__ import annotations

from dataclasses import astuple, dataclass, field

import numpy as np

from ..physics import calibrate, shear
from .level0 import quad_forces, relative_change

QUAD_LEVELS = ("level0", "table", "full")
# Electrodes (C11, C12, C21, C22) → combinations X (eq 30), Y (eq 32), Z (eq 19), R (redundant).
# Rows: electrodes; columns: their weights in X, Y, Z, R.
COMBINATIONS = np.array([[-1, -1, 1, 1], [1, -1, 1, -1], [-1, 1, 1, -1], [1, 1, 1, 1]], dtype=float) / 4.0
_SHEAR_SIGNS = np.array([[-1.0, 1.0, -1.0, 1.0], [-1.0, -1.0, 1.0, 1.0]])  # rows: X, Y sides of each electrode
FAULT_SIGMAS = 8.0
FAULT_RELATIVE = 0.05  # model mismatch allowed in R, as a share of |Z|
NOISE_FLOOR_PF = 2e-4


@dataclass
class QuadModel:
    normal_fit: tuple[float, float, float] = (calibrate.FIT34[0], calibrate.FIT34[1], 0.0)
    shear_a: float = calibrate.FIT35[1]
    shear_b: float = -calibrate.FIT35[0]
    normal_usable_N: float = field(default_factory=lambda: calibrate.fit_usable_force(calibrate.FIT34))
    shear_usable_N: float = field(default_factory=lambda: calibrate.fit_usable_force(calibrate.FIT35))
    coupling: float = 0.0

    def normal_response(self, force_N):
        c2, c1, c0 = self.normal_fit
        f = np.minimum(np.maximum(force_N, 0.0), self.normal_usable_N)
        return (c2 * f + c1) * f + c0

    def forward(self, fxyz_N: np.ndarray) -> np.ndarray:
        """(..., 3) forces → (..., 4) electrode ΔC/C0 (C11, C12, C21, C22)."""
        fxyz = np.asarray(fxyz_N, dtype=float)
        n = self.normal_response(fxyz[..., 2])
        limit = self.shear_usable_N
        txy = shear.shear_response(np.minimum(np.maximum(fxyz[..., :2], -limit), limit), self.shear_a, self.shear_b)
        scale = 1.0 - self.coupling * n
        return n[..., None] + (txy @ _SHEAR_SIGNS) * scale[..., None]

    def inverse(self, relative: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """(..., 4) electrode ΔC/C0 → (..., 3) (Fx, Fy, Fz) and masks of
        shape (...) for normal_out_of_range, shear_out_of_range; plus the
        combinations X, Y, Z and the redundant R under "combinations"."""
        axes = relative @ COMBINATIONS
        forces = np.empty(axes.shape[:-1] + (3,))
        fz, normal_out = calibrate.invert_fit(self.normal_fit, axes[..., 2])
        beyond = fz > self.normal_usable_N
        np.minimum(fz, self.normal_usable_N, out=forces[..., 2])
        shear_axes = axes[..., :2]
        if self.coupling:
            shear_axes = shear_axes / (1.0 - self.coupling * self.normal_response(forces[..., 2]))[..., None]
        # X and Y in one call: the per-call cost dominates at 1 kHz frame by frame.
        fxy, out_xy = shear.shear_force(shear_axes, self.shear_a, self.shear_b)
        limit = self.shear_usable_N
        shear_out = np.logical_or.reduce(out_xy | (np.abs(fxy) > limit), axis=-1)
        np.minimum(np.maximum(fxy, -limit), limit, out=forces[..., :2])
        # A negative normal change below noise is just noise around zero force.
        normal_out = (normal_out & (axes[..., 2] > 0)) | beyond
        return forces, {"normal_out_of_range": normal_out, "shear_out_of_range": shear_out, "combinations": axes}


@dataclass
class QuadProcessor:
    level: str
    model: QuadModel = field(default_factory=QuadModel)
    _noise_for: tuple | None = None
    # Processors with equal keys give the same result on the same input, so
    # their sensors' frames can go through one call.
    batch_key: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.level not in QUAD_LEVELS:
            raise ValueError(f"unknown quad level {self.level!r}; known: {', '.join(QUAD_LEVELS)}")
        self.batch_key = (self.level, astuple(self.model))

    def noise(self, baseline: np.ndarray, baseline_std: np.ndarray) -> float:
        """Noise of the combinations' ΔC/C0 from the tare spread (once per tare)."""
        if self._noise_for is None or self._noise_for[0] is not baseline_std:
            self._noise_for = (baseline_std, float(np.sqrt(np.sum((np.fmax(baseline_std, NOISE_FLOOR_PF) / baseline) ** 2)) / 4.0))
        return self._noise_for[1]

    def process(self, capacitance: np.ndarray, baseline: np.ndarray, noise: np.ndarray | float) -> tuple[np.ndarray, list[list[str]]]:
        """Capacitances (N, 4) pF against baselines (4,) or (N, 4) with the
        combinations' noise (scalar or (N,)) → forces (N, 3) and each frame's flags."""
        if self.level == "level0":
            return quad_forces(capacitance, baseline), [[] for _ in range(len(capacitance))]
        relative = relative_change(capacitance, baseline)
        forces, masks = self.model.inverse(relative)
        combinations = masks.pop("combinations")
        masks["electrode_fault"] = np.abs(combinations[..., 3]) > FAULT_SIGMAS * noise + FAULT_RELATIVE * np.abs(combinations[..., 2])
        if not any(np.count_nonzero(mask) for mask in masks.values()):  # the usual case: no flag on any frame
            return forces, [[] for _ in range(len(forces))]
        names = list(masks)
        table = np.stack([masks[name] for name in names], axis=-1)
        return forces, [[name for name, hit in zip(names, row) if hit] for row in table.tolist()]
