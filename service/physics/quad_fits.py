"""Fits of the quad sensor's models from (force, ΔC/C0) pairs.

Least squares (scipy) in force: the residual of each pair is the model's
force at the measured ΔC/C0 minus the applied force. Parameter standard
errors come from the Jacobian at the optimum, s²·(JᵀJ)⁻¹.

Identifiability: the Yeoh force is linear in S0·C10 and S0·C20, and the
shear response depends on G and the area only through a = d0/(G S^1.5), so
those products are what the data determine; a modulus is then quoted for an
assumed area (the nominal 10×10 mm electrode), never fitted jointly with it.

The paper's own parameters (C10 = 0.03 MPa, C20 = 0.3 MPa) cannot
reproduce its fit (34) for any area: matching the small-force slope needs
S0 = 0.0343⁻¹/(6·0.03) ≈ 162 mm², and with that area C20 = 0.3 MPa makes
the curve far stiffer than measured (see ``paper_parameters_mismatch``).

The default calibration samples the paper's fits (34) and (35) with their
constant terms removed (zero force ⇔ zero ΔC after tare) over the stated
ranges, stopping before each fit turns over (19.06 N and 9.625 N). The
usable range is where the fitted curve's local sensitivity is still at
least ``USABLE_SLOPE_FRACTION`` of its small-force value; beyond it the
service reports a saturated value with a flag.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from . import shear, yeoh
from .paper_data import FIT34, FIT35, NORMAL_RANGE_N, QUAD_DIELECTRIC_MM, QUAD_ELECTRODE_AREA_MM2, SHEAR_RANGE_N

USABLE_SLOPE_FRACTION = 0.1


def fit_curve(coefficients: tuple[float, float, float], force_N: np.ndarray) -> np.ndarray:
    """A paper fit without its constant term (the tare offset)."""
    c2, c1, _ = coefficients
    return c2 * force_N**2 + c1 * force_N


def fit_turning_force(coefficients) -> float:
    c2, c1, _ = coefficients
    return -c1 / (2 * c2)


def fit_usable_force(coefficients) -> float:
    """Force where the fit's slope falls to USABLE_SLOPE_FRACTION of its initial slope."""
    c2, c1, _ = coefficients
    return (1 - USABLE_SLOPE_FRACTION) * c1 / (-2 * c2)


def invert_fit(coefficients, relative: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Force on the rising branch of a fit c2 F² + c1 F + c0 = ΔC/C0.

    Returns (force, out_of_domain). Above the fit's maximum (0.330 for (34),
    0.0382 for (35)) the force is held at the turning force; below c0 (no
    change, or a decrease) it is 0; both are flagged, never NaN and never
    the falling branch.
    """
    c2, c1, c0 = coefficients
    r = np.asarray(relative, dtype=float)
    top = c0 - c1 * c1 / (4 * c2)
    clipped = np.minimum(np.maximum(r, c0), top)  # np.clip's dispatch costs more than the math at 1 frame
    force = 2 * (clipped - c0) / (c1 + np.sqrt(np.maximum(c1 * c1 + 4 * c2 * (clipped - c0), 0.0)))
    return force, (r > top) | (r < c0)


def sample_fit(coefficients, stated_range_N: float, step_N: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(force, ΔC/C0) pairs from a paper fit over its stated range, ending
    before the turn."""
    end = min(stated_range_N, fit_turning_force(coefficients))
    forces = np.arange(0.0, end - 1e-9, step_N)
    return forces, fit_curve(coefficients, forces)


@dataclass(frozen=True)
class FitReport:
    parameters: dict[str, float]
    std_errors: dict[str, float]
    residual_rms_N: float
    residual_max_N: float
    points: int
    usable_range_N: float

    def as_dict(self) -> dict:
        return asdict(self)


def _report(result, names, forces, usable) -> FitReport:
    residuals = result.fun
    dof = max(len(forces) - len(names), 1)
    s2 = float(residuals @ residuals) / dof
    covariance = np.linalg.pinv(result.jac.T @ result.jac) * s2
    return FitReport(
        dict(zip(names, map(float, result.x))),
        dict(zip(names, map(float, np.sqrt(np.diag(covariance))))),
        float(np.sqrt(np.mean(residuals**2))),
        float(np.max(np.abs(residuals))),
        len(forces),
        float(usable),
    )


def fit_yeoh(forces: np.ndarray, relative: np.ndarray, usable_range_N: float) -> FitReport:
    """Fit S0·C10 and S0·C20 (N) to (force, ΔC/C0) pairs."""
    def residual(params):
        return yeoh.normal_force(relative, params[0], params[1]) - forces

    start = (1.0 / (6.0 * max(np.polyfit(forces, relative, 1)[0], 1e-9)), 0.0)
    from scipy.optimize import least_squares  # fitting only: not on the service's start-up path

    result = least_squares(residual, start, x_scale="jac")
    return _report(result, ("c10_area_N", "c20_area_N"), forces, usable_range_N)


def fit_shear(forces: np.ndarray, relative: np.ndarray, usable_range_N: float, paper_form: bool = False) -> FitReport:
    """Fit (a, b) of r = aF − bF² (b = a² when ``paper_form``), residual in force."""
    def residual(params):
        a = params[0]
        b = a * a if paper_form else params[1]
        force, _ = shear.shear_force(relative, a, b)
        return force - forces

    slope = np.polyfit(forces, relative, 1)[0]
    start = (slope,) if paper_form else (slope, 0.0)
    from scipy.optimize import least_squares  # fitting only: not on the service's start-up path

    result = least_squares(residual, start, x_scale="jac")
    return _report(result, ("a_per_N",) if paper_form else ("a_per_N", "b_per_N2"), forces, usable_range_N)


@dataclass(frozen=True)
class QuadCalibration:
    """Calibrated normal and shear models of one quad sensor."""

    c10_area_N: float
    c20_area_N: float
    shear_a_per_N: float
    shear_b_per_N2: float
    normal_usable_N: float
    shear_usable_N: float

    def normal_force(self, relative):
        return yeoh.normal_force(relative, self.c10_area_N, self.c20_area_N)

    def invert_normal(self, relative: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Compressive force and an out-of-domain mask: ΔC/C0 < 0 (the model
        has no tension) or a force past the usable range (held there)."""
        force = np.asarray(self.normal_force(relative), dtype=float)
        out = (np.asarray(relative) < 0) | (force > self.normal_usable_N)
        return np.minimum(force, self.normal_usable_N), out

    def normal_relative(self, force_N: float) -> float:
        """ΔC/C0 at a compressive force (inverse of the monotone Yeoh law)."""
        if force_N <= 0:
            return 0.0
        from scipy.optimize import brentq  # offline only: not on the service's start-up path

        return brentq(lambda r: self.normal_force(r) - force_N, 0.0, 10.0)

    def shear_modulus_MPa(self, area_mm2: float = QUAD_ELECTRODE_AREA_MM2) -> float:
        """G implied by the shear compliance for an assumed area."""
        return QUAD_DIELECTRIC_MM / (self.shear_a_per_N * area_mm2**1.5)


def default_quad_calibration() -> tuple[QuadCalibration, dict[str, FitReport]]:
    """Fit the models to the paper's curves (34) and (35)."""
    normal_usable = fit_usable_force(FIT34)
    shear_usable = fit_usable_force(FIT35)
    fn, rn = sample_fit(FIT34, NORMAL_RANGE_N)
    normal = fit_yeoh(fn[fn <= normal_usable], rn[fn <= normal_usable], normal_usable)
    fs, rs = sample_fit(FIT35, SHEAR_RANGE_N)
    keep = fs <= shear_usable
    tangential = fit_shear(fs[keep], rs[keep], shear_usable)
    paper_shear = fit_shear(fs[keep], rs[keep], shear_usable, paper_form=True)
    calibration = QuadCalibration(
        normal.parameters["c10_area_N"],
        normal.parameters["c20_area_N"],
        tangential.parameters["a_per_N"],
        tangential.parameters["b_per_N2"],
        normal_usable,
        shear_usable,
    )
    return calibration, {"normal_yeoh": normal, "shear": tangential, "shear_paper_form": paper_shear}


def paper_parameters_mismatch() -> dict[str, float]:
    """How far the paper's C10, C20 are from its own fit (34): the area that
    matches the small-force slope, and the force error that area leaves at
    the end of the usable range."""
    area = 1.0 / (6.0 * yeoh.PAPER_C10_MPA * FIT34[1])
    end = fit_usable_force(FIT34)
    r_end = fit_curve(FIT34, end)
    f_paper = float(yeoh.normal_force(r_end, area * yeoh.PAPER_C10_MPA, area * yeoh.PAPER_C20_MPA))
    return {"area_matching_slope_mm2": area, "force_at_fit_end_N": end, "paper_model_force_N": f_paper}
