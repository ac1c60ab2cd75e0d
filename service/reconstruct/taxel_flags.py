"""The per-taxel flags of a grid frame, and those a reading earns before
any force is made of it (grid.py makes the forces).

A channel that did not read is ``no_reading``; one stuck at the same count
for STUCK_FRAMES frames on a board that shows noise is ``stale`` (a
converter that stopped converting repeats an old count: null, as a missing
one); one the tare gave no zero is ``out_of_range`` when its reading lies
outside the tare window and ``no_reading`` while it waits for a late zero.
"""
from __future__ import annotations

import numpy as np

from .baseline import NOISE_FLOOR_PF
from .stuck import STUCK_FRAMES, run_lengths

NO_READING, SATURATED, OUT_OF_RANGE, CROSSTALK_CORRECTED, DRIFT_SUSPECT, STALE, LOADED_AT_TARE = (1 << i for i in range(7))
TAXEL_FLAG_NAMES = {
    NO_READING: "no_reading",
    SATURATED: "saturated",
    OUT_OF_RANGE: "out_of_range",
    CROSSTALK_CORRECTED: "crosstalk_corrected",
    DRIFT_SUSPECT: "drift_suspect",
    STALE: "stale",
    LOADED_AT_TARE: "loaded_at_tare",  # zero from the calibration's C0 (loaded_tare.py) or the stored one (stored_zero.py)
}

# The names of every combination of taxel flags, looked up per frame rather than built.
FLAG_NAMES_BY_BITS = tuple(tuple(name for bit, name in TAXEL_FLAG_NAMES.items() if bits & bit)
                           for bits in range(2 ** len(TAXEL_FLAG_NAMES)))


class ReadingFlags:
    """GridProcessor's flags of a reading, and the stale-channel count they
    keep (``_last_raw``, ``_same_count``; the caches ``_noisy_for`` and
    ``_zero_missing_for``; ``tare_window``: fields of GridProcessor)."""

    def _runs_before(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(last frame (n,) pF, its run lengths (n,)) that this sensor's next
        frames continue (stuck.py); a NaN frame and no runs before the first."""
        if self._last_raw is None or self._last_raw.shape != (n,):
            return np.full(n, np.nan), np.zeros(n, dtype=np.int64)
        return self._last_raw, self._same_count

    @property
    def stale_runs(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(last reading (n,) pF, run lengths (n,)) of the stale-channel count, None before a frame."""
        return None if self._last_raw is None else (self._last_raw, self._same_count)

    def restore_stale_runs(self, last_pF, runs) -> None:
        """Continue another processor's (or a recording's) stale-channel count."""
        self._last_raw, self._same_count = np.array(last_pF, dtype=float), np.array(runs, dtype=np.int64)

    def _stuck(self, capacitance: np.ndarray, counted: tuple | None = None) -> np.ndarray:
        """Run lengths (N, n) of repeated counts in frames (N, n), continuing
        this sensor's runs (stuck.py); ``counted``: (run lengths, last frame)
        already found with other sensors' frames (stuck.stale_rows), only kept."""
        if counted is None:
            previous, prior = self._runs_before(capacitance.shape[1])
            counted = run_lengths(previous[None], prior[None], capacitance[None])[0], capacitance[-1].copy()
        runs, self._last_raw = counted
        self._same_count = runs[-1]
        return runs
    def _reading_flags(self, capacitance: np.ndarray, baseline: np.ndarray,
                       baseline_std: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(no-reading, stale and no-zero bits of (N, n) frames, the stale
        readings' mask or None). A stale reading (a converter that stopped
        converting repeats an old count) gives no force of now: null, as
        a missing one. Flags are set with ``where=`` masks: at 1 kHz the
        number of numpy calls, not their arithmetic, is the cost."""
        flags = np.isnan(capacitance).astype(np.uint8)  # NO_READING is bit 0
        stale = None
        if self._noisy_board(baseline_std):
            stale = self._stuck(capacitance) >= STUCK_FRAMES
            if np.count_nonzero(stale):
                np.bitwise_or(flags, STALE, out=flags, where=stale)
            else:
                stale = None
        self.flag_missing_zero(flags, capacitance, baseline)
        return flags, stale

    def flag_missing_zero(self, flags: np.ndarray, capacitance: np.ndarray, baseline: np.ndarray) -> None:
        """A channel the tare gave no zero (baseline NaN: no plausible
        reading in its window) has no force. Where it reads, say why: a
        reading outside the tare window (level0.py; e.g. a channel stuck at
        the converter's top since power-up) is ``out_of_range``, a
        plausible one still waiting for its late zero (baseline.py)
        ``no_reading``. Once per tare the usual answer is that every
        channel has its zero."""
        if self._zero_missing_for is None or self._zero_missing_for[0] is not baseline:
            missing = np.isnan(baseline)
            self._zero_missing_for = (baseline, missing if missing.any() else None)
        missing = self._zero_missing_for[1]
        if missing is None:
            return
        reads = missing & ~np.isnan(capacitance)
        if self.tare_window is None:
            outside = reads
        else:
            outside = reads & ((capacitance < self.tare_window[0]) | (capacitance > self.tare_window[1]))
        np.bitwise_or(flags, OUT_OF_RANGE, out=flags, where=outside)
        np.bitwise_or(flags, NO_READING, out=flags, where=reads & ~outside)

    def _noisy_board(self, baseline_std_pF: np.ndarray) -> bool:
        """Whether the converter shows noise at all (else equal counts in a
        row are normal and stuck channels cannot be told). Once per tare."""
        if self._noisy_for is None or self._noisy_for[0] is not baseline_std_pF:
            self._noisy_for = (baseline_std_pF, bool(np.nanmax(baseline_std_pF, initial=0.0) > NOISE_FLOOR_PF))
        return self._noisy_for[1]
