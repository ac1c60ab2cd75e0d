"""Capacitance of a taxel from the Ritz deflection (paper 000 eqs 18–19).

Eq (19) integrates the parallel-plate density over the electrode,
C = ∫ εr ε0 / g(x, y) dA with the local gap g = d0 + w(upper electrode) −
w(lower electrode) (w positive upward; the paper drops the lower electrode's
0.35 nm, we keep it). Eq (18) scales the deflection linearly with force,
w_F = w_q0 · F / (q0 S_F): the plate is linear elastic, so one solve per
load shape gives the whole ΔC/C0(F) curve. The curve is nonlinear only
through 1/g, and ends where the gap would close: past ``max_gap_closure``
of d0 the model is not trusted (PDMS stiffens long before contact) and the
table stops, so the service reports saturation there, never a capacitance
from a negative gap.

The paper writes the constant as 1/(4πk) with k = 9.0e9; that gives
C0 = 10.66 pF for the 3×3 mm electrode, εr 2.68, d0 = 20 µm. With the exact
ε0 it is 10.68 pF; only ratios ΔC/C0 enter the product, so the difference
does not matter, but ``c0_pF`` reports both.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .ritz import RitzSolution, Taxel

EPSILON_0 = 8.8541878128e-12  # F/m
PAPER_K = 9.0e9  # the paper's "static electricity constant", 1/(4π ε0) rounded
PDMS_EPSILON_R = 2.68
MAX_GAP_CLOSURE = 0.5


def c0_pF(taxel: Taxel, epsilon_r: float = PDMS_EPSILON_R, paper_constant: bool = False) -> float:
    """Undeformed parallel-plate capacitance of the (square) electrode in pF."""
    area_m2 = (2 * taxel.half_electrode_um * 1e-6) ** 2
    eps0 = 1.0 / (4 * np.pi * PAPER_K) if paper_constant else EPSILON_0
    return epsilon_r * eps0 * area_m2 / (taxel.gap_um * 1e-6) * 1e12


@dataclass(frozen=True)
class GapField:
    """Gap change per newton over the electrode quarter, on a quadrature grid.

    ``dgap_per_N`` (µm/N) and ``weights`` (µm²) have shape (n, n); the
    quarter's weights sum to (half electrode)². Negative = closing.
    """

    d0_um: float
    dgap_per_N: np.ndarray
    weights: np.ndarray

    def relative_change(self, force_N: np.ndarray) -> np.ndarray:
        """ΔC/C0 at forces (shape (m,)); NaN where the gap closes by more
        than MAX_GAP_CLOSURE of d0 anywhere on the electrode."""
        force_N = np.atleast_1d(np.asarray(force_N, dtype=float))
        gaps = self.d0_um + force_N[:, None, None] * self.dgap_per_N[None]
        c = (self.weights[None] / gaps).sum(axis=(1, 2))
        c0 = self.weights.sum() / self.d0_um
        out = c / c0 - 1.0
        out[force_N > self.max_force_N] = np.nan
        return out

    @property
    def max_force_N(self) -> float:
        """Force at which the gap first closes by MAX_GAP_CLOSURE of d0."""
        closing = -self.dgap_per_N.min()
        return np.inf if closing <= 0 else MAX_GAP_CLOSURE * self.d0_um / closing


def _electrode_quadrature(solution: RitzSolution, points: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Gauss points and weights along one side of the electrode quarter (the
    electrode edge is a break of the partition, so the rule is exact per element)."""
    x, w, _ = solution.bases[0].quadrature(points)
    inside = x < solution.taxel.half_electrode_um
    return x[inside], w[inside]


def _between_electrodes(solution: RitzSolution, component: str, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Upper minus lower electrode displacement (µm) on the grid x × y."""
    taxel = solution.taxel
    z = taxel.interfaces_um
    return (solution.displacement(component, x, y, z[taxel.upper_electrode_interface])
            - solution.displacement(component, x, y, z[taxel.lower_electrode_interface]))


def gap_field(solution: RitzSolution, force_of_solution_N: float, electrode_points: int | None = None) -> GapField:
    """Gap change per newton over the electrode from a solution computed for
    a load of total force ``force_of_solution_N`` (over the full unit)."""
    x, w = _electrode_quadrature(solution, electrode_points)
    dgap = _between_electrodes(solution, "w", x, x) / force_of_solution_N
    return GapField(solution.taxel.gap_um, dgap, np.outer(w, w))


def sensitivity_per_N(field: GapField, forces_N: np.ndarray | None = None) -> float:
    """Least-squares slope of ΔC/C0 against force over 0–10 N in 1 N steps
    (how the paper measured its table 1 sensitivities)."""
    forces_N = np.arange(0.0, 11.0) if forces_N is None else forces_N
    slope, _ = np.polyfit(forces_N, field.relative_change(forces_N), 1)
    return float(slope)


def shear_relative_change(solution: RitzSolution, force_of_solution_N: float, forces_N: np.ndarray, points: int | None = None) -> np.ndarray:
    """ΔC/C0 of the whole electrode under a shear load along +x.

    The solution is the quarter model with w odd and u even in x. Two
    effects: the gap tilts (w odd: a second-order change of 1/g over the
    whole electrode) and the upper electrode slides by s = u(upper) −
    u(lower), so a strip of width F·s at its leading edge no longer faces
    the lower electrode (parallel-plate, fringe fields neglected).
    Returns shape (len(forces_N),).
    """
    taxel = solution.taxel
    x, w = _electrode_quadrature(solution, points)
    dgap = _between_electrodes(solution, "w", x, x) / force_of_solution_N
    edge = np.array([taxel.half_electrode_um])
    slide = _between_electrodes(solution, "u", edge, x)[0] / force_of_solution_N
    dgap_edge = _between_electrodes(solution, "w", edge, x)[0] / force_of_solution_N
    d0 = taxel.gap_um
    forces = np.atleast_1d(np.asarray(forces_N, dtype=float))
    area = np.outer(w, w)
    tilt = [(area * (1 / (d0 + f * dgap) + 1 / (d0 - f * dgap))).sum() for f in forces]
    lost = [(w * np.abs(f * slide) / (d0 + f * dgap_edge)).sum() for f in forces]
    c0 = 2 * area.sum() / d0
    return (np.array(tilt) - np.array(lost)) / c0 - 1.0
