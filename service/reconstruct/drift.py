"""Common-mode drift of a grid, followed on its unloaded taxels.

Temperature and the fatigue creep of paper 001 §5.2 move every taxel's
capacitance together; a press moves the few taxels under the contact. So
the drift is the median relative change of the taxels that read within
``band`` noise of the frame's median (the unloaded ones), smoothed by an
exponential average with time constant ``tau_s`` (short: the median of many
taxels is already quiet, and a long average would lag a moving drift).
The median ignores a press on a minority of taxels however slow it is; the
estimate is frozen while fewer than half the valid taxels are unloaded (a
plate over the whole array — a uniform press and a drift cannot be told
apart), and frames are flagged ``drift_suspect`` once that has lasted
``suspect_after_s``, or while the drift exceeds ``max_drift``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def masked_median(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Row medians of (N, n) ``values`` over the True entries of ``mask``;
    NaN for a row with none. (np.nanmedian goes through masked arrays and
    costs ~100 µs a row.)"""
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)
    count = np.count_nonzero(mask, axis=1)
    rows = np.arange(len(values))
    middle = (ordered[rows, np.maximum((count - 1) // 2, 0)] + ordered[rows, count // 2]) / 2
    return np.where(count > 0, middle, np.nan)


@dataclass
class DriftTracker:
    tau_s: float = 0.2
    band: float = 4.0
    max_drift: float = 0.01
    suspect_after_s: float = 10.0
    drift: float = 0.0
    _last_t: float | None = None
    _frozen_since: float | None = None

    def reset(self) -> None:
        self.drift, self._last_t, self._frozen_since = 0.0, None, None

    def update(self, relative: np.ndarray, noise: np.ndarray, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Feed frames (N, n) of ΔC/C0 at times (N,) s; return the drift after
        each frame (N,) and which frames are drift-suspect (N,)."""
        if len(relative) == 1:  # the live path's common case, in a third of the numpy calls
            medians, enough = self._quiet_median(relative[0], noise)
            drift, suspect = self._step(float(t_s[0]), enough, medians)
            return np.array([drift]), np.array([suspect])
        valid = ~np.isnan(relative)
        centre = masked_median(relative, valid)
        quiet = valid & (np.abs(relative - centre[:, None]) < self.band * noise)
        enough = (quiet.sum(axis=1) * 2 >= valid.sum(axis=1)) & quiet.any(axis=1)
        medians = masked_median(relative, quiet)
        out = np.empty(len(relative))
        suspect = np.zeros(len(relative), dtype=bool)
        for i, (t, ok, median) in enumerate(zip(t_s.tolist(), enough.tolist(), medians.tolist())):
            out[i], suspect[i] = self._step(t, ok, median)
        return out, suspect

    def _quiet_median(self, row: np.ndarray, noise: np.ndarray) -> tuple[float, bool]:
        """One frame (n,): median of its quiet taxels, and whether they are enough."""
        ordered = np.sort(row)  # NaN sorts last
        valid = np.count_nonzero(ordered == ordered)
        if not valid:
            return float("nan"), False
        centre = (ordered[(valid - 1) // 2] + ordered[valid // 2]) / 2
        quiet = np.sort(row[np.abs(row - centre) < self.band * noise])  # NaN compares False, silently
        n = quiet.size
        if not n or n * 2 < valid:
            return float("nan"), False
        return float((quiet[(n - 1) // 2] + quiet[n // 2]) / 2), True

    def _step(self, t: float, enough: bool, median: float) -> tuple[float, bool]:
        """Advance the exponential average to board time ``t``."""
        dt = 0.0 if self._last_t is None else min(max(t - self._last_t, 0.0), self.tau_s)
        self._last_t = t
        if enough:
            self.drift += (median - self.drift) * (dt / self.tau_s)
            self._frozen_since = None
        elif self._frozen_since is None:
            self._frozen_since = t
        frozen_long = self._frozen_since is not None and t - self._frozen_since >= self.suspect_after_s
        return self.drift, frozen_long or abs(self.drift) > self.max_drift
