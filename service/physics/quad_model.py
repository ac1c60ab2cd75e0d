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
simulator uses ``forward``, the reconstruction ``inverse``. A linear normal
curve (c2 = 0) is inverted as F = (ΔC/C0)/c1.

Uploaded calibrations (``QuadModel.from_fits``, reached by
``PUT /sensors/{id}/calibration``) must be physically plausible, else
ValueError naming the field and the reason:

* ``normal_fit`` [c2, c1] (ΔC/C0 = c2 F² + c1 F): both finite; c1, the
  small-force slope, in SLOPE_RANGE_PER_N = (0.001, 1) per N (fit 34:
  0.0343); c2 ≤ 0 (the curve saturates, it does not steepen) with the
  usable range 0.9·c1/(2|c2|) (where the slope has fallen to 10 % of c1,
  before the turning point c1/(2|c2|)) at least MIN_USABLE_N = 1 N, i.e.
  |c2| ≤ 0.45·c1. c2 = 0 (a linear curve) is accepted. The usable range is
  capped at MAX_USABLE_N = 50 N (what a linear or nearly linear curve gets).
* ``shear_fit`` [a, b] (ΔC/C0 = a F − b F²): both finite; a in (0.001, 1)
  per N (fit 35: 0.0077); b ≥ 0 with 0.9·a/(2b) ≥ 1 N, i.e. b ≤ 0.45·a;
  b = 0 accepted; capped at 50 N likewise.
* optional ``normal_usable_N``, ``shear_usable_N`` (a calibration session's
  own: where the sensor's response stopped rising): at least MIN_USABLE_N;
  they narrow the curves' usable ranges, never widen them.
* and then the model itself: ``forward`` evaluated on a dense grid over
  [0, usable] (normal) and [−usable, usable] (shear) must be finite and
  strictly increasing, and ``inverse`` must give the forces back (within
  1e-6 N + 1e-6 relative), so every reading the service will meet has a
  finite answer.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import shear
from .paper_data import FIT34, FIT35, QUAD_DIELECTRIC_MM, QUAD_ELECTRODE_AREA_MM2
from .quad_fits import fit_usable_force, invert_fit

# The paper gives no C0: ε0·εr·S/d with S = 10×10 mm², d = 2 mm and an
# assumed εr = 5, 2.2 pF per electrode. Only a reference before the first tare.
NOMINAL_C0_PF = 8.854e-3 * 5.0 * QUAD_ELECTRODE_AREA_MM2 / QUAD_DIELECTRIC_MM
SLOPE_RANGE_PER_N = (1e-3, 1.0)  # plausible small-force slopes c1 (normal) and a (shear), per N
MIN_USABLE_N = 1.0  # an uploaded curve must be usable at least this far
MAX_USABLE_N = 50.0  # usable range of a linear (or nearly linear) uploaded curve
USABLE_SLOPE_FRACTION = 0.1  # the usable range ends where the slope is 10 % of its initial value
CHECK_POINTS = 2001
ROUND_TRIP_TOLERANCE_N = 1e-6

# Electrodes (C11, C12, C21, C22) → combinations X (eq 30), Y (eq 32), Z (eq 19), R (redundant).
# Rows: electrodes; columns: their weights in X, Y, Z, R.
_COMBINATIONS = np.array([[-1, -1, 1, 1], [1, -1, 1, -1], [-1, 1, 1, -1], [1, 1, 1, 1]], dtype=float) / 4.0


def combinations(relative: np.ndarray) -> np.ndarray:
    """Electrode ΔC/C0 (..., 4), order C11, C12, C21, C22 → (..., 4) as
    X = (r12 + r22 − r11 − r21)/4, Y = (r21 + r22 − r11 − r12)/4,
    Z = (r11 + r12 + r21 + r22)/4 and the redundant R = (r11 + r22 − r12 −
    r21)/4. Through einsum's own loop, not a matrix product: BLAS sums a
    (1, 4) and a (16, 4) product in different orders on some CPUs (AVX-512),
    and a quad's forces depended on how many frames a read held; einsum sums
    every row alike (as crosstalk.py's unmixing)."""
    return np.einsum("...j,jk->...k", relative, _COMBINATIONS)

_SHEAR_SIGNS = np.array([[-1.0, 1.0, -1.0, 1.0], [-1.0, -1.0, 1.0, 1.0]])  # rows: X, Y sides of each electrode


@dataclass
class QuadModel:
    normal_fit: tuple[float, float, float] = (FIT34[0], FIT34[1], 0.0)
    shear_a: float = FIT35[1]
    shear_b: float = -FIT35[0]
    normal_usable_N: float = field(default_factory=lambda: fit_usable_force(FIT34))
    shear_usable_N: float = field(default_factory=lambda: fit_usable_force(FIT35))
    coupling: float = 0.0

    @classmethod
    def from_fits(cls, normal_fit, shear_fit, coupling: float = 0.0,
                  normal_usable_N: float | None = None, shear_usable_N: float | None = None) -> QuadModel:
        """A model from an uploaded calibration, checked (module docstring);
        ValueError names the field and the reason. ``coupling`` c ≥ 0 (the
        shear response scaled by 1 − c·n(Fz)) must leave at least a tenth
        of it at the normal curve's usable end. ``normal_usable_N``,
        ``shear_usable_N``: where the calibration session's response stopped
        rising (quad_fit.py), which can come before the curve's own usable end;
        they only narrow it."""
        c2, c1 = _pair("normal_fit", normal_fit, ("c2", "c1"))
        a, b = _pair("shear_fit", shear_fit, ("a", "b"))
        low, high = SLOPE_RANGE_PER_N
        if not low < c1 < high:
            raise ValueError(f"normal_fit: c1 = {c1} per N is outside the plausible range ({low}, {high})")
        if c2 > 0:
            raise ValueError(f"normal_fit: c2 = {c2} must be ≤ 0 (a compressive curve saturates, it does not steepen)")
        if not low < a < high:
            raise ValueError(f"shear_fit: a = {a} per N is outside the plausible range ({low}, {high})")
        if b < 0:
            raise ValueError(f"shear_fit: b = {b} must be ≥ 0 (ΔC/C0 = a F − b F²)")
        normal_usable = _narrowed("normal_usable_N", _usable("normal_fit", "c2", c1, -c2), normal_usable_N)
        shear_usable = _narrowed("shear_usable_N", _usable("shear_fit", "b", a, b), shear_usable_N)
        if isinstance(coupling, bool) or not isinstance(coupling, (int, float)):
            raise ValueError(f"coupling: expected a number, got {coupling!r}")
        coupling = float(coupling)
        largest = max_coupling((c2, c1), normal_usable)
        if not (math.isfinite(coupling) and 0.0 <= coupling <= largest):
            raise ValueError(f"coupling: c = {coupling} must be ≥ 0 and leave a tenth of the shear response at "
                             f"{normal_usable:.3g} N (c ≤ {largest:.3g})")
        model = cls((c2, c1, 0.0), a, b, normal_usable, shear_usable, coupling)
        model.check()
        return model

    def check(self) -> None:
        """ValueError unless forward is finite and strictly increasing over
        the usable ranges and inverse gives the forces back."""
        for name, axis, limit, start in (("normal_fit", 2, self.normal_usable_N, 0.0),
                                         ("shear_fit", 0, self.shear_usable_N, -self.shear_usable_N)):
            force = np.linspace(start, limit, CHECK_POINTS)
            fxyz = np.zeros((CHECK_POINTS, 3))
            fxyz[:, axis] = force
            with np.errstate(all="ignore"):
                relative = self.forward(fxyz)
                # electrode C22 rises with both Fz and Fx
                curve = relative[:, 3]
                if not (np.isfinite(relative).all() and np.all(np.diff(curve) > 0)):
                    raise ValueError(f"{name}: the curve is not finite and strictly increasing over "
                                     f"[{start:g}, {limit:g}] N")
                back, _ = self.inverse(relative)
            error = np.abs(back[:, axis] - force)
            if not (np.isfinite(back).all() and np.all(error <= ROUND_TRIP_TOLERANCE_N * (1 + np.abs(force)))):
                raise ValueError(f"{name}: the inverse does not give the forces back over [{start:g}, {limit:g}] N "
                                 f"(worst error {np.nanmax(error, initial=np.inf):.3g} N)")

    @property
    def top_relative(self) -> float:
        """Largest electrode ΔC/C0 within the calibrated ranges: the normal
        curve at its usable end plus the shear curve at its own."""
        normal = float(self.normal_response(self.normal_usable_N))
        limit = self.shear_usable_N
        return normal + float(self.shear_a * limit - self.shear_b * limit * limit)

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
        axes = combinations(relative)
        forces = np.empty(axes.shape[:-1] + (3,))
        if self.normal_fit[0] == 0:  # linear: invert_fit's turning point would divide by zero
            c1, c0 = self.normal_fit[1], self.normal_fit[2]
            fz = np.maximum(axes[..., 2] - c0, 0.0) / c1
            normal_out = axes[..., 2] < c0
        else:
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


def max_coupling(normal_fit, normal_usable_N: float) -> float:
    """The largest coupling c a model holds: the one that leaves a tenth of
    the shear response at the normal curve's usable end, from ``normal_fit``
    [c2, c1] and that end (N)."""
    c2, c1 = normal_fit
    return 0.9 / ((c2 * normal_usable_N + c1) * normal_usable_N)


def _pair(field_name: str, values, names: tuple[str, str]) -> tuple[float, float]:
    """Two finite floats from an upload field, else ValueError naming it."""
    try:
        first, second = (float(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(f"{field_name}: expected two numbers [{names[0]}, {names[1]}], got {values!r}") from None
    for name, value in zip(names, (first, second)):
        if not np.isfinite(value):
            raise ValueError(f"{field_name}: {name} = {value} is not finite")
    return first, second


def _usable(field_name: str, name: str, slope: float, bend: float) -> float:
    """Usable force of r = slope·F − bend·F²: where its slope falls to
    USABLE_SLOPE_FRACTION of ``slope``, capped at MAX_USABLE_N; ValueError
    below MIN_USABLE_N."""
    if bend == 0:
        return MAX_USABLE_N
    usable = (1 - USABLE_SLOPE_FRACTION) * slope / (2 * bend)
    if not usable >= MIN_USABLE_N:
        turn = slope / (2 * bend)
        raise ValueError(f"{field_name}: |{name}| = {bend:g} puts the curve's turning point at {turn:.3g} N "
                         f"(usable to {usable:.3g} N); it must be usable to at least {MIN_USABLE_N:g} N, "
                         f"i.e. |{name}| ≤ {(1 - USABLE_SLOPE_FRACTION) * slope / (2 * MIN_USABLE_N):.3g}")
    return min(usable, MAX_USABLE_N)


def _narrowed(field_name: str, usable: float, top) -> float:
    """The curve's usable force, narrowed to a measured ``top`` (None: not
    measured); ValueError unless it is a number of at least MIN_USABLE_N."""
    if top is None:
        return usable
    if isinstance(top, bool) or not isinstance(top, (int, float)) or not top >= MIN_USABLE_N:
        raise ValueError(f"{field_name}: {top!r} must be a force of at least {MIN_USABLE_N:g} N")
    return min(usable, float(top))
