"""Crosstalk of a grid, compensated and estimated.

The forward model (mechanical coupling r_meas = (I + K) r_true and the
multiplexer's leakage m_k = (1 − α) C_k + α C_(k−1)) is physics, in
physics/crosstalk_model.py. Mechanical compensation multiplies ΔC/C0 by
(I + K)⁻¹ (precomputed). The leakage is an FIR filter along the scan
(row-major order within a frame); compensation is its inverse IIR, applied
to the raw capacitances and to the baseline alike. The IIR over one
64-channel frame is applied as its (n, n) impulse-response matrix: one call
whatever the batch, and the same summation order for every row.
Detection (``CrosstalkEstimator``): isolated single-taxel loads — one taxel
well above noise, every taxel beyond its 3×3 neighbourhood at noise level,
its neighbours below a few % of it. The mechanical coefficient is the mean
neighbour response relative to the loaded taxel; the electrical fraction is
the asymmetry between the two same-row neighbours, the one scanned next
minus the one scanned before (mechanically they are alike), scaled back to
capacitance. Estimates are least-squares slopes over events, with their count.
An unread channel (NaN: dead or implausible) is an unknown load: it spoils
the events whose read channels its load could move, and no others.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..physics.crosstalk_model import PAPER_MECHANICAL_COUPLING, check_coefficients, neighbour_matrix



@dataclass
class Crosstalk:
    """Compensation for one grid; coefficients may be refined at run time."""

    rows: int
    cols: int
    mechanical: float = PAPER_MECHANICAL_COUPLING
    electrical: float = 0.0
    _neighbours: np.ndarray = field(init=False, repr=False)
    _unmix: np.ndarray = field(init=False, repr=False)
    _unleak_for: tuple | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        check_coefficients(self.mechanical, self.electrical)
        self._neighbours = neighbour_matrix(self.rows, self.cols)
        self.set_mechanical(self.mechanical)

    def set_mechanical(self, coupling: float) -> None:
        self.mechanical = coupling
        mixing = np.eye(self.rows * self.cols) + coupling * self._neighbours
        self._unmix = np.linalg.inv(mixing).T  # row vectors: r_true = r_meas @ unmix

    def unmix_mechanical(self, relative: np.ndarray) -> np.ndarray:
        """(..., n) measured → compensated ΔC/C0 (NaN channels count as 0)."""
        # einsum's own loop gives every row the same summation order whatever
        # the batch size (BLAS does not), so forces do not depend on how the
        # stream was cut into batches.
        missing = np.isnan(relative)
        if not np.count_nonzero(missing):
            return np.einsum("...j,jk->...k", relative, self._unmix)
        out = np.einsum("...j,jk->...k", np.where(missing, 0.0, relative), self._unmix)
        return np.where(missing, np.nan, out)

    def leak(self, capacitance: np.ndarray) -> np.ndarray:
        """What the multiplexer reads, (..., n) pF: each channel (1 − α) of
        its own and α of the one scanned before it (the first: of nothing),
        the filter ``unleak`` inverts."""
        out = (1.0 - self.electrical) * np.asarray(capacitance, dtype=float)
        out[..., 1:] += self.electrical * np.asarray(capacitance)[..., :-1]
        return out

    def unleak(self, capacitance: np.ndarray, fill: np.ndarray) -> np.ndarray:
        """Undo the leakage, (..., n) pF. A channel with no reading is taken
        as ``fill`` (its baseline) for what it leaks into the next one."""
        if self.electrical == 0.0:
            return capacitance
        missing = np.isnan(capacitance)
        if not np.count_nonzero(missing):
            return np.einsum("...j,jk->...k", capacitance, self._unleak_matrix())
        out = np.einsum("...j,jk->...k", np.where(missing, fill, capacitance), self._unleak_matrix())
        return np.where(missing, np.nan, out)

    def _unleak_matrix(self) -> np.ndarray:
        """(n, n) matrix M with row vectors unleaked = measured @ M: column k
        is the inverse IIR's response at channel k to each earlier channel."""
        if self._unleak_for is None or self._unleak_for[0] != self.electrical:
            self._unleak_for = (self.electrical, unleak_matrix(self.rows * self.cols, self.electrical))
        return self._unleak_for[1]


def unleak_matrix(n: int, electrical: float) -> np.ndarray:
    """(n, n) impulse responses of the inverse leakage filter
    y[k] = (x[k] − e·y[k−1])/(1 − e): row j is the response to channel j,
    (1/(1 − e))·(−e/(1 − e))^(k − j) for k ≥ j, 0 before. Closed form (the
    recurrence's, as scipy.signal.lfilter would give it: tests check it),
    so the live path does not import scipy.signal (0.4 s at start-up)."""
    steps = np.arange(n)
    lag = steps[None, :] - steps[:, None]
    ratio = -electrical / (1.0 - electrical)
    with np.errstate(divide="ignore", invalid="ignore"):
        powers = np.where(lag >= 0, ratio ** np.maximum(lag, 0), 0.0)
    return powers / (1.0 - electrical)


@dataclass
class _Slope:
    """Least-squares slope through the origin, y ≈ k x, from running sums."""

    xy: float = 0.0
    xx: float = 0.0
    events: int = 0
    yy: float = 0.0

    def add(self, x: np.ndarray, y: np.ndarray) -> None:
        self.xy += float(x @ y)
        self.xx += float(x @ x)
        self.yy += float(y @ y)
        self.events += len(x)

    def standard_error(self) -> float:
        """Of the slope, from the residuals' spread (inf with fewer than 2 events)."""
        if self.events < 2 or self.xx <= 0:
            return float("inf")
        residual = max(self.yy - self.xy * self.xy / self.xx, 0.0)
        return float(np.sqrt(residual / (self.events - 1) / self.xx))

    def summary(self) -> dict:
        return {"estimate": self.xy / self.xx if self.events else None, "events": self.events}


@dataclass
class CrosstalkEstimator:
    """Estimates both coefficients from isolated single-taxel loads, as
    least-squares slopes against the loaded taxel's ΔC/C0 (strong loads
    weigh most, where the neighbours' share stands clear of the noise)."""

    rows: int
    cols: int
    min_snr: float = 40.0
    max_neighbour_share: float = 0.05
    mechanical: _Slope = field(default_factory=_Slope)
    electrical: _Slope = field(default_factory=_Slope)

    def __post_init__(self) -> None:
        self._near = neighbour_matrix(self.rows, self.cols).astype(bool)
        n = self.rows * self.cols
        col = np.arange(n) % self.cols
        self._has_row_pair = (col > 0) & (col < self.cols - 1)
        after = np.zeros((n, n), dtype=bool)
        inner = np.flatnonzero(self._has_row_pair)
        after[inner, inner + 1] = True
        self._symmetric = self._near & ~after  # neighbours without the one scanned next
        # What a peak's event reads: the peak and its eight neighbours (the
        # channels scanned before and after it among them). A load on channel d
        # moves d, its neighbours (coupling) and the channel scanned after it
        # (leakage); an unread d may hide one, so it spoils the peaks whose
        # read channels that load would reach, and no other.
        read = self._near | np.eye(n, dtype=bool)
        reach = read.copy()
        reach[np.arange(n - 1), np.arange(1, n)] = True
        self._spoiled_by = (read.astype(np.int16) @ reach.T.astype(np.int16)) > 0  # (peak, unread channel)

    def observe(self, relative: np.ndarray, noise: np.ndarray, baseline_pF: np.ndarray) -> None:
        """Feed frames of ΔC/C0 (N, n) (or one frame (n,)) with the noise (n,)
        and baseline (n,) they were computed with."""
        relative = np.atleast_2d(relative)
        snr = relative / noise
        if not np.nanmax(snr, initial=-np.inf) >= self.min_snr:  # the usual frame: nothing strong enough
            return
        peak = np.argmax(np.nan_to_num(snr, nan=-np.inf), axis=1)
        rows = np.arange(len(relative))
        peak_r = relative[rows, peak]
        candidate = (snr[rows, peak] >= self.min_snr) & self._has_row_pair[peak]
        if not candidate.any():
            return
        relative, snr, peak, peak_r = relative[candidate], snr[candidate], peak[candidate], peak_r[candidate]
        unread = np.isnan(relative)
        if np.count_nonzero(unread):  # a dead or implausible channel: out of reach it neither counts nor hides a load
            usable = ~np.any(unread & self._spoiled_by[peak], axis=1)
            if not usable.any():
                return
            relative, snr, peak, peak_r = relative[usable], snr[usable], peak[usable], peak_r[usable]
            relative = np.where(np.isnan(relative), 0.0, relative)  # only channels the event does not read
        near = self._near[peak]
        far = ~near
        far[np.arange(len(peak)), peak] = False
        isolated = ~np.any(far & (np.abs(snr) > 4.0), axis=1)
        isolated &= ~np.any(near & (np.abs(relative / peak_r[:, None]) > self.max_neighbour_share), axis=1)
        if not isolated.any():
            return
        relative, peak, peak_r = relative[isolated], peak[isolated], peak_r[isolated]
        idx = np.arange(len(peak))
        before, after = relative[idx, peak - 1], relative[idx, peak + 1]
        # The channel scanned next sees α ΔC_peak on top of the mechanical share:
        # (after − before) · C0_after / C0_peak = α · r_peak.
        self.electrical.add(peak_r, (after - before) * baseline_pF[peak + 1] / baseline_pF[peak])
        symmetric = self._symmetric[peak]
        self.mechanical.add(peak_r, (relative * symmetric).sum(axis=1) / symmetric.sum(axis=1))

    def report(self) -> dict:
        return {"mechanical": self.mechanical.summary(), "electrical": self.electrical.summary()}
