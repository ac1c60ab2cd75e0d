"""Shear model of the quad sensor (paper 001 §2.2, eqs 20–29).

A tangential force F on the surface area S shears the dielectric
(thickness d0, shear modulus G): γ = F/(G S), and the upper electrode
(side L = √S) slides by δ = d0 tan γ ≈ d0 γ. Eq (28) writes the relative
overlap change as

    r = ΔS/S0 = a F − b F²,   with a = d0/(G S^(3/2)) and, in the paper, b = a².

The quadratic term comes from (L − δ)², the overlap of a shift along both
axes, while the linear term is that of a shift along one axis; for a pure
x shift the overlap change is exactly linear. We keep the paper's form but
treat b as its own parameter (the measured fit (35) has b ≈ 7 a², which the
paper ascribes to slip at the interface).

Other errors in the paper: eq (20) repeats eq (2) (a gap change) for what
is an area change, ΔC_X = εε0 (S − S0)/d0; eq (22) drops the sign (an
electrode whose overlap shrinks loses capacitance); eq (27) writes
(1 + μ)/(E √S0) for the linear term but (1 + μ)/(S0 E) squared for the
quadratic one, which is consistent only with the two-axis shift above.

Inverse (eq 29 generalised): F = (a − √(a² − 4 b r)) / (2 b), the branch
through F = 0, evaluated as 2r / (a + √(a² − 4 b r)) to avoid cancellation
at small r. It exists only for r ≤ a²/(4b) (the paper's √(1 − 4x),
x ≤ 0.25, when b = a²); beyond, and at the turning force a/(2b), the model
has no answer: ``shear_force`` returns the turning force and a flag instead
of NaN.
"""
from __future__ import annotations

import numpy as np


def paper_coefficients(d0_mm: float, shear_modulus_MPa: float, area_mm2: float) -> tuple[float, float]:
    """(a, b) of eq (28): a = d0/(G S^1.5) per N, b = a²."""
    a = d0_mm / (shear_modulus_MPa * area_mm2**1.5)
    return a, a * a


def shear_response(force_N: np.ndarray, a: float, b: float) -> np.ndarray:
    """r = a|F| − b F², signed like F (the +X electrodes gain overlap)."""
    f = np.abs(np.asarray(force_N, dtype=float))
    return np.sign(force_N) * (a * f - b * f * f)


def turning_force(a: float, b: float) -> float:
    return np.inf if b <= 0 else a / (2.0 * b)


def shear_force(relative: np.ndarray, a: float, b: float) -> tuple[np.ndarray, np.ndarray]:
    """Invert eq (28) for signed ΔC/C0; return (force N, out_of_domain mask).

    Out of domain (|r| ≥ a²/(4b)): the force is held at ± the turning force
    and flagged, never NaN and never the other root.
    """
    r = np.asarray(relative, dtype=float)
    magnitude = np.abs(r)
    if b <= 0:
        return r / a, np.zeros(r.shape, dtype=bool)
    limit = a * a / (4.0 * b)
    out = magnitude >= limit
    clipped = np.minimum(magnitude, limit)
    force = 2.0 * clipped / (a + np.sqrt(np.maximum(a * a - 4.0 * b * clipped, 0.0)))
    return np.sign(r) * force, out
