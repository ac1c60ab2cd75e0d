"""Grid reconstruction at every fidelity level, per frame or in batches.

Levels (cheapest first):

``level0``  F = (ΔC/C0)/s, linear, signed (see level0.py).
``table``   per-taxel inversion of the model table (taxel.py): the gap
            nonlinearity, saturation at the table's top, no negative forces.
``full``    table + multiplexer leakage and mechanical crosstalk
            compensation (crosstalk.py) + common-mode drift tracking
            (drift.py) + crosstalk detection.

Every level flags per taxel: no reading, saturated, out of range; ``full``
adds crosstalk-corrected and drift-suspect; a channel stuck at the same
count for STUCK_FRAMES frames is flagged stale. Inputs are capacitances in
pF, shape (n,) per frame or (N, n) per batch, and the sensor's baseline (n,).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..calibration import GridCalibration
from . import level0
from .crosstalk import Crosstalk, CrosstalkEstimator
from .drift import DriftTracker
from .taxel import TaxelResponse

NO_READING, SATURATED, OUT_OF_RANGE, CROSSTALK_CORRECTED, DRIFT_SUSPECT, STALE = (1 << i for i in range(6))
TAXEL_FLAG_NAMES = {
    NO_READING: "no_reading",
    SATURATED: "saturated",
    OUT_OF_RANGE: "out_of_range",
    CROSSTALK_CORRECTED: "crosstalk_corrected",
    DRIFT_SUSPECT: "drift_suspect",
    STALE: "stale",
}
GRID_LEVELS = ("level0", "table", "full")
STUCK_FRAMES = 50
NOISE_FLOOR_PF = 2e-4  # never trust a noise estimate below 0.2 fF
CORRECTION_SIGMAS = 3.0


def flag_names(bits: int) -> list[str]:
    return [name for bit, name in TAXEL_FLAG_NAMES.items() if bits & bit]


@dataclass
class GridResult:
    forces_N: np.ndarray  # (..., n), NaN = no reading
    taxel_flags: np.ndarray  # (..., n) uint8 bit set
    frame_flags: list[str]


@dataclass
class GridProcessor:
    """Reconstruction of one grid sensor at one level."""

    level: str
    calibration: GridCalibration
    response: TaxelResponse | None = None
    crosstalk: Crosstalk | None = None
    drift: DriftTracker = field(default_factory=DriftTracker)
    estimator: CrosstalkEstimator | None = None
    _last_raw: np.ndarray | None = None
    _same_count: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.level not in GRID_LEVELS:
            raise ValueError(f"unknown grid level {self.level!r}; known: {', '.join(GRID_LEVELS)}")
        if self.level != "level0" and self.response is None:
            raise ValueError(f"level {self.level!r} needs a taxel response table")
        if self.level == "full":
            self.crosstalk = self.crosstalk or Crosstalk(self.calibration.rows, self.calibration.cols)
            self.estimator = self.estimator or CrosstalkEstimator(self.calibration.rows, self.calibration.cols)

    def reset(self) -> None:
        """Forget tracked state (after a tare)."""
        self.drift.reset()

    def noise(self, baseline_pF: np.ndarray, baseline_std_pF: np.ndarray) -> np.ndarray:
        """Noise of ΔC/C0 per taxel, from the tare window's spread."""
        return np.fmax(baseline_std_pF, NOISE_FLOOR_PF) / baseline_pF

    def _stuck(self, capacitance: np.ndarray) -> np.ndarray:
        if self._last_raw is None or self._last_raw.shape != capacitance.shape:
            self._same_count = np.zeros(capacitance.shape, dtype=np.int64)
        else:
            same = capacitance == self._last_raw
            self._same_count = np.where(same, self._same_count + 1, 0)
        self._last_raw = capacitance.copy()
        return self._same_count >= STUCK_FRAMES

    def process(self, capacitance: np.ndarray, baseline: np.ndarray, baseline_std: np.ndarray, t_s: float) -> GridResult:
        """One frame: capacitance (n,) pF → forces (n,) N and flags."""
        flags = np.where(np.isnan(capacitance), NO_READING, 0).astype(np.uint8)
        frame_flags: list[str] = []
        if baseline_std.max() > NOISE_FLOOR_PF:
            flags |= np.where(self._stuck(capacitance), STALE, 0).astype(np.uint8)
        if self.level == "level0":
            return GridResult(level0.grid_forces(capacitance, baseline, self.calibration), flags, frame_flags)
        noise = self.noise(baseline, baseline_std)
        if self.level == "table":
            relative = level0.relative_change(capacitance, baseline)
        else:
            relative, corrected, suspect = self._compensate(capacitance, baseline, noise, t_s)
            flags |= np.where(corrected, CROSSTALK_CORRECTED, 0).astype(np.uint8)
            if suspect:
                flags |= DRIFT_SUSPECT
                frame_flags.append("drift_suspect")
        forces, saturated, out_of_range = self.response.inverse(relative, noise)
        flags |= np.where(saturated, SATURATED, 0).astype(np.uint8)
        flags |= np.where(out_of_range, OUT_OF_RANGE, 0).astype(np.uint8)
        return GridResult(forces, flags, frame_flags)

    def _compensate(self, capacitance, baseline, noise, t_s):
        crosstalk = self.crosstalk
        unleaked = crosstalk.unleak(capacitance, baseline)
        unleaked_baseline = crosstalk.unleak(baseline, baseline)
        raw_relative = capacitance / baseline - 1.0
        relative = unleaked / unleaked_baseline - 1.0
        suspect = self.drift.update(relative, noise, t_s)
        relative = DriftTracker.correct(relative, self.drift.drift)
        self.estimator.observe(relative, noise, baseline)
        relative = crosstalk.unmix_mechanical(relative)
        corrected = np.abs(relative - DriftTracker.correct(raw_relative, self.drift.drift)) > CORRECTION_SIGMAS * noise
        return relative, corrected, suspect

    def process_batch(self, capacitance: np.ndarray, baseline: np.ndarray, baseline_std: np.ndarray, t_s: np.ndarray) -> GridResult:
        """Frames (N, n) pF at times (N,) → forces (N, n). Same results as
        ``process`` frame by frame, except that stuck-channel detection and
        crosstalk detection are left to the streaming path."""
        flags = np.where(np.isnan(capacitance), NO_READING, 0).astype(np.uint8)
        if self.level == "level0":
            return GridResult(level0.grid_forces(capacitance, baseline, self.calibration), flags, [])
        noise = self.noise(baseline, baseline_std)
        frame_flags: list[str] = []
        if self.level == "table":
            relative = capacitance / baseline - 1.0
        else:
            crosstalk = self.crosstalk
            unleaked = crosstalk.unleak(capacitance, baseline)
            relative = unleaked / crosstalk.unleak(baseline, baseline) - 1.0
            raw_relative = capacitance / baseline - 1.0
            drift = np.empty(len(relative))
            suspect = False
            for i in range(len(relative)):
                suspect |= self.drift.update(relative[i], noise, float(t_s[i]))
                drift[i] = self.drift.drift
            relative = crosstalk.unmix_mechanical(DriftTracker.correct(relative, drift[:, None]))
            corrected = np.abs(relative - DriftTracker.correct(raw_relative, drift[:, None])) > CORRECTION_SIGMAS * noise
            flags |= np.where(corrected, CROSSTALK_CORRECTED, 0).astype(np.uint8)
            if suspect:
                frame_flags.append("drift_suspect")
        forces, saturated, out_of_range = self.response.inverse(relative, noise)
        flags |= np.where(saturated, SATURATED, 0).astype(np.uint8) | np.where(out_of_range, OUT_OF_RANGE, 0).astype(np.uint8)
        return GridResult(forces, flags, frame_flags)
