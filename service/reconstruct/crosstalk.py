"""Crosstalk of a grid: mechanical coupling and multiplexer leakage.

Mechanical. A loaded taxel pulls its eight neighbours' capacitance down:
paper 000 measured −0.015 … −0.019 % on the neighbours of U44 while it rose
6.1 % at 5.21 N, i.e. about −0.28 % of the loaded taxel's ΔC/C0 each. In
ΔC/C0 space the measured image is r_meas = (I + K) r_true with K the
neighbour coupling; compensation multiplies by (I + K)⁻¹ (precomputed).

Electrical. The multiplexer does not settle fully, so a channel reads a
fraction α of the channel scanned just before it (row-major order within a
frame): m_k = (1 − α) C_k + α C_(k−1). This is an FIR filter along the scan;
compensation is its inverse IIR (scipy.signal.lfilter), applied to the raw
capacitances and to the baseline alike.

Detection (``CrosstalkEstimator``): isolated single-taxel loads — one taxel
well above noise, every taxel beyond its 3×3 neighbourhood at noise level,
its neighbours below a few % of it. The mechanical coefficient is the mean
neighbour response relative to the loaded taxel; the electrical fraction is
the asymmetry between the two same-row neighbours, the one scanned next
minus the one scanned before (mechanically they are alike), scaled back to
capacitance. Estimates are medians over events, with their count.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

PAPER_MECHANICAL_COUPLING = -0.0028  # neighbour ΔC/C0 per unit ΔC/C0 of the loaded taxel


def neighbour_matrix(rows: int, cols: int) -> np.ndarray:
    """(n, n) 0/1 matrix of the eight-neighbourhood, row-major taxels."""
    r, c = np.divmod(np.arange(rows * cols), cols)
    dr = np.abs(r[:, None] - r[None, :])
    dc = np.abs(c[:, None] - c[None, :])
    return ((dr <= 1) & (dc <= 1) & ~((dr == 0) & (dc == 0))).astype(float)


@dataclass
class Crosstalk:
    """Compensation for one grid; coefficients may be refined at run time."""

    rows: int
    cols: int
    mechanical: float = PAPER_MECHANICAL_COUPLING
    electrical: float = 0.0
    _neighbours: np.ndarray = field(init=False, repr=False)
    _unmix: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not -0.05 < self.mechanical <= 0.05:
            raise ValueError(f"mechanical coupling {self.mechanical} is outside (-0.05, 0.05]")
        if not 0.0 <= self.electrical < 0.5:
            raise ValueError(f"electrical leakage fraction {self.electrical} is outside [0, 0.5)")
        self._neighbours = neighbour_matrix(self.rows, self.cols)
        self.set_mechanical(self.mechanical)

    def set_mechanical(self, coupling: float) -> None:
        self.mechanical = coupling
        mixing = np.eye(self.rows * self.cols) + coupling * self._neighbours
        self._unmix = np.linalg.inv(mixing).T  # row vectors: r_true = r_meas @ unmix

    def mix_mechanical(self, relative: np.ndarray) -> np.ndarray:
        """Forward model (for the simulator): (..., n) true → measured ΔC/C0."""
        return relative + self.mechanical * relative @ self._neighbours

    def unmix_mechanical(self, relative: np.ndarray) -> np.ndarray:
        """(..., n) measured → compensated ΔC/C0 (NaN channels count as 0)."""
        missing = np.isnan(relative)
        out = np.where(missing, 0.0, relative) @ self._unmix
        return np.where(missing, np.nan, out)

    def leak(self, capacitance: np.ndarray) -> np.ndarray:
        """Forward model: what the multiplexer reads, (..., n) pF."""
        if self.electrical == 0.0:
            return capacitance
        return lfilter([1.0 - self.electrical, self.electrical], [1.0], capacitance, axis=-1)

    def unleak(self, capacitance: np.ndarray, fill: np.ndarray) -> np.ndarray:
        """Undo the leakage, (..., n) pF. A channel with no reading is taken
        as ``fill`` (its baseline) for what it leaks into the next one."""
        if self.electrical == 0.0:
            return capacitance
        missing = np.isnan(capacitance)
        filled = np.where(missing, fill, capacitance)
        out = lfilter([1.0], [1.0 - self.electrical, self.electrical], filled, axis=-1)
        return np.where(missing, np.nan, out)


@dataclass
class CrosstalkEstimator:
    """Estimates both coefficients from isolated single-taxel loads."""

    rows: int
    cols: int
    min_snr: float = 40.0
    max_neighbour_share: float = 0.05
    mechanical_samples: list = field(default_factory=list)
    electrical_samples: list = field(default_factory=list)

    def observe(self, relative: np.ndarray, noise: np.ndarray, baseline_pF: np.ndarray) -> None:
        """Feed one frame of ΔC/C0 (n,) with its noise (n,) and baseline (n,)."""
        if np.isnan(relative).any():
            return
        snr = relative / noise
        peak = int(np.argmax(snr))
        if snr[peak] < self.min_snr:
            return
        pr, pc = divmod(peak, self.cols)
        r, c = np.divmod(np.arange(relative.size), self.cols)
        near = (np.abs(r - pr) <= 1) & (np.abs(c - pc) <= 1)
        if np.any(np.abs(snr[~near]) > 4.0):
            return
        neighbours = near.copy()
        neighbours[peak] = False
        share = relative[neighbours] / relative[peak]
        if np.any(np.abs(share) > self.max_neighbour_share):
            return
        if 0 < pc < self.cols - 1:  # both same-row neighbours exist
            before, after = relative[peak - 1], relative[peak + 1]
            # after: α ΔC_peak / C0_after on top of the mechanical share.
            delta_c = relative[peak] * baseline_pF[peak]
            self.electrical_samples.append((after - before) * baseline_pF[peak + 1] / delta_c)
            symmetric = neighbours.copy()
            symmetric[peak + 1] = False
            self.mechanical_samples.append(float(np.mean(relative[symmetric]) / relative[peak]))

    def report(self) -> dict:
        def summary(samples):
            if not samples:
                return {"estimate": None, "events": 0}
            return {"estimate": float(np.median(samples)), "events": len(samples),
                    "spread": float(np.subtract(*np.percentile(samples, [75, 25])))}

        return {"mechanical": summary(self.mechanical_samples), "electrical": summary(self.electrical_samples)}
