"""Crosstalk of a grid, forward: mechanical coupling and multiplexer leakage.

Mechanical. A loaded taxel pulls its eight neighbours' capacitance down:
paper 000 measured −0.015 … −0.019 % on the neighbours of U44 while it rose
6.1 % at 5.21 N, i.e. about −0.28 % of the loaded taxel's ΔC/C0 each. In
ΔC/C0 space the measured image is r_meas = (I + K) r_true with K the
neighbour coupling (K = coupling × the eight-neighbourhood).

Electrical. The multiplexer does not settle fully, so a channel reads a
fraction α of the channel scanned just before it (row-major order within a
frame): m_k = (1 − α) C_k + α C_(k−1).

The simulator applies this model; the reconstruction undoes it
(reconstruct/crosstalk.py).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

PAPER_MECHANICAL_COUPLING = -0.0028  # neighbour ΔC/C0 per unit ΔC/C0 of the loaded taxel


def check_coefficients(mechanical: float, electrical: float) -> None:
    """ValueError naming a coefficient outside what the models are valid for."""
    if not -0.05 < mechanical <= 0.05:
        raise ValueError(f"mechanical coupling {mechanical} is outside (-0.05, 0.05]")
    if not 0.0 <= electrical < 0.5:
        raise ValueError(f"electrical leakage fraction {electrical} is outside [0, 0.5)")


def neighbour_matrix(rows: int, cols: int) -> np.ndarray:
    """(n, n) 0/1 matrix of the eight-neighbourhood, row-major taxels."""
    r, c = np.divmod(np.arange(rows * cols), cols)
    dr = np.abs(r[:, None] - r[None, :])
    dc = np.abs(c[:, None] - c[None, :])
    return ((dr <= 1) & (dc <= 1) & ~((dr == 0) & (dc == 0))).astype(float)


@dataclass(frozen=True)
class CrosstalkModel:
    """Forward crosstalk of one rows × cols grid."""

    rows: int
    cols: int
    mechanical: float = PAPER_MECHANICAL_COUPLING
    electrical: float = 0.0
    _neighbours: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        check_coefficients(self.mechanical, self.electrical)
        object.__setattr__(self, "_neighbours", neighbour_matrix(self.rows, self.cols))

    def mix_mechanical(self, relative: np.ndarray) -> np.ndarray:
        """(..., n) true → measured ΔC/C0."""
        return relative + self.mechanical * relative @ self._neighbours

    def leak(self, capacitance: np.ndarray) -> np.ndarray:
        """What the multiplexer reads, (..., n) pF."""
        if self.electrical == 0.0:
            return capacitance
        from scipy.signal import lfilter  # the simulator's: not on the service's start-up path

        return lfilter([1.0 - self.electrical, self.electrical], [1.0], capacitance, axis=-1)
