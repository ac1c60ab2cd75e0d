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

A frame needs MIN_REFERENCE_TAXELS valid taxels to be a reference at all:
one pressed taxel is left out only where the frame's median lies on an
unloaded one. A lone taxel is its own median (a 1×1 grid's press was taken
for drift: 2.8 N of a 3.7 N press, then out of range after its release);
two taxels' median is their mean, so half a press under two bands is taken
for drift and neither is quiet above it. With three, one press leaves the
median on an unloaded taxel. Below that the estimate is frozen, as under a
plate: no correction, and ``drift_suspect`` after ``suspect_after_s`` —
except on a grid of fewer taxels (grid.py), which never has a reference:
its drift is not tracked, as at the table level, and no frame says so.

Times are the board's clock, which wraps every 2³² µs and starts again
from 0 when the board restarts: followed as one unwrapped time (a step back
within MAX_WRAP_STEP_S of the wrap is the wrap; any other step back, a
restart, continues from the last frame's time), so neither keeps a frozen
estimate unflagged until the clock catches up again (71.6 min after a
wrap, as long as the board had run before a restart).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

T_WRAP_S = 2**32 * 1e-6
MAX_WRAP_STEP_S = 1.0  # a step back this close to the wrap is the wrap (scans come at least once a second)
MIN_REFERENCE_TAXELS = 3  # valid taxels a frame needs for its median to ignore a one-taxel press (docstring)


def quiet_medians(relative: np.ndarray, band: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame of (N, n) ΔC/C0: the median of the quiet taxels (within
    ``band`` — (n,) or (N, n) — of the frame's median), and whether they are
    enough (at least half the valid ones, of at least MIN_REFERENCE_TAXELS;
    the median means nothing where not). Both (N,). Rows are independent,
    so frames of several sensors can go through one call. (np.nanmedian
    goes through masked arrays and costs ~100 µs a row.)"""
    if len(relative) == 1:  # one frame: a third of the numpy calls
        median, enough = _quiet_median(relative[0], band if band.ndim == 1 else band[0])
        return np.array([median]), np.array([enough])
    rows = np.arange(len(relative))
    ordered = np.sort(relative, axis=1)  # NaN sorts last
    n = relative.shape[1]
    if (ordered[:, -1] == ordered[:, -1]).all():  # no NaN (NaN ≠ NaN): every row's middle is in one column
        valid = n
        centre = (ordered[:, (n - 1) // 2] + ordered[:, n // 2]) / 2
    else:
        valid = np.sum(relative == relative, axis=1)
        centre = (ordered[rows, np.maximum(valid - 1, 0) // 2] + ordered[rows, valid // 2]) / 2
    quiet = np.abs(relative - centre[:, None]) < band  # NaN compares False
    count = np.count_nonzero(quiet, axis=1)
    ordered = np.sort(np.where(quiet, relative, np.inf), axis=1)
    medians = (ordered[rows, np.maximum(count - 1, 0) // 2] + ordered[rows, count // 2]) / 2
    return medians, (count * 2 >= valid) & (valid >= MIN_REFERENCE_TAXELS)  # so count ≥ 2


def _quiet_median(row: np.ndarray, band: np.ndarray) -> tuple[float, bool]:
    ordered = np.sort(row)  # NaN sorts last
    valid = np.count_nonzero(ordered == ordered)
    if valid < MIN_REFERENCE_TAXELS:
        return float("nan"), False
    centre = (ordered[(valid - 1) // 2] + ordered[valid // 2]) / 2
    quiet = np.sort(row[np.abs(row - centre) < band])  # NaN compares False, silently
    n = quiet.size
    if n * 2 < valid:  # valid ≥ 3: none quiet is not enough either
        return float("nan"), False
    return float((quiet[(n - 1) // 2] + quiet[n // 2]) / 2), True


@dataclass
class DriftTracker:
    tau_s: float = 0.2
    band: float = 4.0
    max_drift: float = 0.01
    suspect_after_s: float = 10.0
    drift: float = 0.0
    _last_t: float | None = None  # the last frame's board time as sent (s)
    _frozen_since: float | None = None  # unwrapped (board time + _offset)
    _offset: float = 0.0  # unwrapped − sent: 0 until the clock wraps or the board restarts

    def reset(self) -> None:
        self.drift, self._last_t, self._frozen_since, self._offset = 0.0, None, None, 0.0

    def follow(self, t_s: list[float], enough: list[bool], medians: list[float]) -> list[tuple[float, bool]]:
        """Advance through frames at times ``t_s`` given their quiet medians
        and whether those were enough (``quiet_medians``, as lists: the
        recurrence is scalar, and a live read holds a frame or two per
        sensor); return each frame's drift and whether it is drift-suspect.
        The exponential average is advanced to each board time ``t`` by
        dt = t − last (clipped to [0, tau_s]); one loop with locals, as an
        offline replay steps every frame of a log through it."""
        tau, suspect_after, max_drift = self.tau_s, self.suspect_after_s, self.max_drift
        drift, last, frozen_since, offset = self.drift, self._last_t, self._frozen_since, self._offset
        out = []
        for t, ok, median in zip(t_s, enough, medians):
            if last is not None and t < last:  # the clock wrapped, or the board restarted (module docstring)
                offset += T_WRAP_S if t + T_WRAP_S - last <= MAX_WRAP_STEP_S else last - t
            dt = 0.0 if last is None else min(max(t - last, 0.0), tau)
            last = t
            now = t + offset
            if ok:
                drift += (median - drift) * (dt / tau)
                frozen_since = None
            elif frozen_since is None:
                frozen_since = now
            out.append((drift, (frozen_since is not None and now - frozen_since >= suspect_after)
                        or abs(drift) > max_drift))
        self.drift, self._last_t, self._frozen_since, self._offset = drift, last, frozen_since, offset
        return out
