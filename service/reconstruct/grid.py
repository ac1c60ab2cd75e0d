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
ADOPT_AFTER_EVENTS = 50  # isolated loads needed before a detected coefficient replaces the prior
ADOPT_PERIOD_FRAMES = 256  # estimates are adopted only at multiples of this frame count
ESTIMATE_EVERY = 4


def flag_names(bits: int) -> list[str]:
    return [name for bit, name in TAXEL_FLAG_NAMES.items() if bits & bit]


@dataclass
class GridResult:
    forces_N: np.ndarray  # (N, n), NaN = no reading
    taxel_flags: np.ndarray  # (N, n) uint8 bit set, see TAXEL_FLAG_NAMES


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
    _noise_for: tuple | None = None
    _noisy_for: tuple | None = None
    _reference_for: tuple | None = None
    adopted_events: int = 0
    _frames_seen: int = 0
    _sampled: list = field(default_factory=list)  # (ΔC/C0 rows, noise, baseline) awaiting the estimator

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
        """Noise of ΔC/C0 per taxel from the tare window's spread. The
        converter's noise is one figure for all channels, and 100 frames give
        each channel's spread only to ±7 %, so the median over channels is
        used (in pF), divided by each taxel's baseline."""
        if self._noise_for is None or self._noise_for[0] is not baseline_std_pF:
            pooled = np.nanmedian(baseline_std_pF) if np.isfinite(baseline_std_pF).any() else 0.0
            self._noise_for = (baseline_std_pF, max(pooled, NOISE_FLOOR_PF) / baseline_pF)
        return self._noise_for[1]

    def _stuck(self, capacitance: np.ndarray) -> np.ndarray:
        """(N, n) mask of channels that have repeated the same count for
        STUCK_FRAMES frames in a row (a converter that stopped converting;
        with real noise two equal counts in a row are already rare)."""
        previous = self._last_raw if self._last_raw is not None and self._last_raw.shape == capacitance.shape[1:] else None
        if len(capacitance) == 1 and previous is not None:  # the live path's common case
            self._same_count = np.where(capacitance[0] == previous, self._same_count + 1, 0)
            self._last_raw = capacitance[0].copy()
            return self._same_count[None] >= STUCK_FRAMES
        prior = self._same_count if previous is not None else np.zeros(capacitance.shape[1], dtype=np.int64)
        shifted = np.vstack([previous[None] if previous is not None else np.full((1, capacitance.shape[1]), np.nan), capacitance[:-1]])
        same = capacitance == shifted
        if not np.count_nonzero(same):  # with converter noise, the usual batch: every run restarts
            self._last_raw, self._same_count = capacitance[-1].copy(), np.zeros(capacitance.shape[1], dtype=np.int64)
            return np.zeros(capacitance.shape, dtype=bool)
        # Run lengths of `same` along the frames, continuing the previous batch's runs.
        runs = np.cumsum(same, axis=0)
        resets = np.maximum.accumulate(np.where(same, 0, runs), axis=0)
        counts = runs - resets + np.where(np.cumprod(same, axis=0).astype(bool), prior, 0)
        self._last_raw, self._same_count = capacitance[-1].copy(), counts[-1]
        return counts >= STUCK_FRAMES

    def process(self, capacitance: np.ndarray, baseline: np.ndarray, baseline_std: np.ndarray, t_s: np.ndarray) -> GridResult:
        """Frames (N, n) pF at board times (N,) s → forces (N, n) N and
        per-taxel flags (N, n). A single frame is a batch of one."""
        # Flags are set with ``where=`` masks: at 1 kHz frame by frame the
        # number of numpy calls, not their arithmetic, is the cost.
        flags = np.isnan(capacitance).astype(np.uint8)  # NO_READING is bit 0
        if self._noisy_board(baseline_std):
            np.bitwise_or(flags, STALE, out=flags, where=self._stuck(capacitance))
        if self.level == "level0":
            return GridResult(level0.grid_forces(capacitance, baseline, self.calibration), flags)
        noise = self.noise(baseline, baseline_std)
        if self.level == "table":
            relative = level0.relative_change(capacitance, baseline)
        else:
            relative, corrected, suspect = self._compensate(capacitance, baseline, noise, t_s)
            np.bitwise_or(flags, CROSSTALK_CORRECTED, out=flags, where=corrected)
            if np.count_nonzero(suspect):
                np.bitwise_or(flags, DRIFT_SUSPECT, out=flags, where=suspect[:, None] & (flags & NO_READING == 0))
        forces, saturated, out_of_range = self.response.inverse(relative, noise)
        np.bitwise_or(flags, SATURATED, out=flags, where=saturated)
        np.bitwise_or(flags, OUT_OF_RANGE, out=flags, where=out_of_range)
        return GridResult(forces, flags)

    def _noisy_board(self, baseline_std_pF: np.ndarray) -> bool:
        """Whether the converter shows noise at all (else equal counts in a
        row are normal and stuck channels cannot be told). Once per tare."""
        if self._noisy_for is None or self._noisy_for[0] is not baseline_std_pF:
            self._noisy_for = (baseline_std_pF, bool(np.nanmax(baseline_std_pF, initial=0.0) > NOISE_FLOOR_PF))
        return self._noisy_for[1]

    def _compensate(self, capacitance, baseline, noise, t_s):
        """Leakage → drift → mechanical unmixing, on (N, n) frames at (N,) times.
        Returns compensated ΔC/C0, the crosstalk-corrected mask and the
        drift-suspect mask (N,).

        Refined coefficients take effect only at multiples of
        ADOPT_PERIOD_FRAMES frames, so the result does not depend on how the
        stream was cut into batches (a replay equals the live run)."""
        if len(capacitance) <= ADOPT_PERIOD_FRAMES - self._frames_seen % ADOPT_PERIOD_FRAMES - 1:
            # The whole batch lies inside one adoption period: no slicing needed.
            result = self._compensate_segment(capacitance, baseline, noise, t_s)
            self._frames_seen += len(capacitance)
            return result
        parts = []
        start = 0
        while start < len(capacitance):
            end = min(len(capacitance), start + ADOPT_PERIOD_FRAMES - self._frames_seen % ADOPT_PERIOD_FRAMES)
            parts.append(self._compensate_segment(capacitance[start:end], baseline, noise, t_s[start:end]))
            self._frames_seen += end - start
            if self._frames_seen % ADOPT_PERIOD_FRAMES == 0:
                self._observe_sampled()
                self._adopt_estimates()
            start = end
        return tuple(np.concatenate(arrays) for arrays in zip(*parts))

    def _compensate_segment(self, capacitance, baseline, noise, t_s):
        crosstalk = self.crosstalk
        ratio = crosstalk.unleak(capacitance, baseline) / self._reference(baseline)
        drift, suspect = self.drift.update(ratio - 1.0, noise, t_s)
        scale = 1.0 + drift[:, None]
        relative = ratio / scale - 1.0  # drift removed: (1 + r)/(1 + d) − 1
        # Every ESTIMATE_EVERY-th frame (by frame count, so batching does not matter)
        # is plenty for coefficients that change over hours; they are observed
        # together once per adoption period, which costs far less than per frame.
        first = -self._frames_seen % ESTIMATE_EVERY
        if first < len(relative):
            self._sampled.append((relative[first::ESTIMATE_EVERY], noise, baseline))
        compensated = crosstalk.unmix_mechanical(relative)
        uncompensated = capacitance / (baseline * scale) - 1.0
        corrected = np.abs(compensated - uncompensated) > CORRECTION_SIGMAS * noise
        return compensated, corrected, suspect

    def _reference(self, baseline: np.ndarray) -> np.ndarray:
        """The baseline as the multiplexer would read it without leakage;
        recomputed only after a tare or a new leakage fraction."""
        electrical = self.crosstalk.electrical
        cached = self._reference_for
        if cached is None or cached[0] is not baseline or cached[1] != electrical:
            cached = self._reference_for = (baseline, electrical, self.crosstalk.unleak(baseline, baseline))
        return cached[2]

    def _observe_sampled(self) -> None:
        """Feed the estimator the frames sampled this period, one call per tare."""
        sampled, self._sampled = self._sampled, []
        while sampled:
            _, noise, baseline = sampled[0]
            same = 0
            while same < len(sampled) and sampled[same][1] is noise and sampled[same][2] is baseline:
                same += 1
            self.estimator.observe(np.concatenate([rows for rows, _, _ in sampled[:same]]), noise, baseline)
            sampled = sampled[same:]

    def _adopt_estimates(self) -> None:
        """Refine the coefficients from the data once enough isolated loads
        were seen. The mechanical slope is measured before unmixing, so it is
        the coupling itself and keeps accumulating; the electrical one is
        measured after the leakage already compensated, so it is a residual:
        added to the fraction in use, then measured afresh."""
        estimator, crosstalk = self.estimator, self.crosstalk
        if estimator.electrical.events < ADOPT_AFTER_EVENTS:
            return
        report = estimator.report()
        crosstalk.electrical = float(np.clip(crosstalk.electrical + report["electrical"]["estimate"], 0.0, 0.3))
        crosstalk.set_mechanical(float(np.clip(report["mechanical"]["estimate"], -0.02, 0.0)))
        self.adopted_events += estimator.electrical.events
        estimator.electrical = type(estimator.electrical)()
