"""Yeoh model of the quad sensor's dielectric under normal force (paper 001 §2.1).

Derivation (incompressible, uniaxial compression along z). With the stretch
λ = d/d0 < 1 along z and λ1 = λ2 = λ^(−1/2) across, I1 = λ² + 2/λ. For
W = C10 (I1 − 3) + C20 (I1 − 3)², ∂W/∂I1 = C10 + 2 C20 (I1 − 3), the
Cauchy stress along z is σ = 2 (λ² − 1/λ) ∂W/∂I1 (lateral stresses zero fix
the pressure), and the nominal stress is P = σ/λ = 2 (λ − λ⁻²) ∂W/∂I1. The
force on the reference area S0 is F = −P S0, positive in compression:

    F = 2 S0 (λ⁻² − λ) [C10 + 2 C20 (I1 − 3)].

Errors in the paper: eqs (11)–(14) and (17)–(18) square (I1 − 3) inside
∂W/∂I1 (the derivative of C20 (I1 − 3)² is 2 C20 (I1 − 3)); eq (18) has the
sign of a tensile force (2 S0 (λ − λ⁻²) is negative in compression); and
eq (9)'s compressible term is written for J with D_i but the model is then
used as incompressible, which is consistent only because J = 1.

Capacitance: C ∝ 1/d with a fixed electrode area (eq 4), so
λ = C0/C = 1/(1 + ΔC/C0). Units: C10, C20 in MPa, S0 in mm² → F in N.

Only the products S0·C10 and S0·C20 enter F: area and moduli cannot be told
apart by force–capacitance data (see ``calibrate``).
"""
from __future__ import annotations

import numpy as np

PAPER_C10_MPA = 0.03
PAPER_C20_MPA = 0.3


def stretch_from_relative_change(relative: np.ndarray) -> np.ndarray:
    """λ = d/d0 from ΔC/C0 (ΔC/C0 > −1)."""
    return 1.0 / (1.0 + np.asarray(relative, dtype=float))


def normal_force(relative: np.ndarray, c10_area_N: float, c20_area_N: float) -> np.ndarray:
    """Compressive force (N) from ΔC/C0, for S0·C10 and S0·C20 in N
    (MPa·mm²). Valid for ΔC/C0 ≥ 0; negative ΔC/C0 gives a tensile (negative)
    force, which a caller treats as out of range."""
    lam = stretch_from_relative_change(relative)
    i1 = lam**2 + 2.0 / lam
    return 2.0 * (lam**-2 - lam) * (c10_area_N + 2.0 * c20_area_N * (i1 - 3.0))

