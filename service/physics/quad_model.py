"""The quad sensor's model: (Fx, Fy, Fz) ↔ electrode ΔC/C0, forward and inverse.

Electrode ij (sx, sy = ±1 on the +X/+Y side, r = ΔC/C0):

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
(1 − c·n(Fz)).

Out of the calibrated range (past the usable force, or a ΔC/C0 the curve
never reaches, or a negative normal change) the force is held at the range's
end and flagged, never taken from the falling branch of a fit. The
simulator uses ``forward``, the reconstruction ``inverse``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import shear
from .paper_data import FIT34, FIT35
from .quad_fits import fit_usable_force, invert_fit

# Electrodes (C11, C12, C21, C22) → combinations X (eq 30), Y (eq 32), Z (eq 19), R (redundant).
# Rows: electrodes; columns: their weights in X, Y, Z, R.
COMBINATIONS = np.array([[-1, -1, 1, 1], [1, -1, 1, -1], [-1, 1, 1, -1], [1, 1, 1, 1]], dtype=float) / 4.0
_SHEAR_SIGNS = np.array([[-1.0, 1.0, -1.0, 1.0], [-1.0, -1.0, 1.0, 1.0]])  # rows: X, Y sides of each electrode


@dataclass
class QuadModel:
    normal_fit: tuple[float, float, float] = (FIT34[0], FIT34[1], 0.0)
    shear_a: float = FIT35[1]
    shear_b: float = -FIT35[0]
    normal_usable_N: float = field(default_factory=lambda: fit_usable_force(FIT34))
    shear_usable_N: float = field(default_factory=lambda: fit_usable_force(FIT35))
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
        fz, normal_out = invert_fit(self.normal_fit, axes[..., 2])
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
