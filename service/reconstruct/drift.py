"""Common-mode drift of a grid, followed on its unloaded taxels.

Temperature and the fatigue creep of paper 001 §5.2 move every taxel's
capacitance together; a press moves the few taxels under the contact. So
the drift is seen in the median relative change of the taxels that read
within ``band`` noise of the frame's median (the unloaded ones): it ignores
a press on a minority of taxels however slow it is. The estimate is frozen
while fewer than half the valid taxels are unloaded.

A flat object over the whole array, or most of it, leaves the loaded taxels
"quiet" at the load's level: the median alone cannot tell it from drift (a
0.6 N/taxel plate over an 8×8 was taken for drift within 0.2 s and read
0 N; over 6×6, the unloaded rest read below zero). What tells them apart
is speed. Drift is slow: PDMS's thermal expansion (~3×10⁻⁴/K) and its
permittivity move C0 by the order of 0.1–0.3 %/K, a skin's temperature
changes by a few kelvin a minute at most, and creep without a load is
slower still; a load moves the level within a touch. So:

* the level may have moved since the estimate last agreed with the quiet
  median (the anchor) by at most the reach, MAX_RATE_PER_S times the time
  since: 1 % ΔC/C0 a minute, a 3 K/min ramp at 0.3 %/K, twice the
  0.5 %/min we track, under which genuine drift stays. The estimate is the
  median's exponential average (``tau_s``: the median of many taxels is
  already quiet, a long average would lag) kept within the reach of the
  anchor, so it follows nothing faster than drift moves;
* a median whose average stands further from the anchor than the reach
  plus a band of noise (what noise and a minority press's rank shift move
  it by) is a load, and so is one further than a taxel's noise from its
  average (a press or a release under way: drift moves it by rate × tau_s,
  ~0), and one moving faster than the bound: its average further from its
  slower average (``tau_slow_s``) than drift at the bound sets them apart,
  plus GAP_SIGMAS times that gap's own noise. A median of m quiet taxels
  varies by (π/2)σ²/m, and the gap carries a share of it, followed frame by
  frame through the two averages' variances and covariance: 0.036 of the
  median's σ at 500 Hz, 0.0056 of a taxel's over 64 taxels. The σ/4 this replaced was
  ~40 times that: it let ramps by up to 1 %/min + σ/1.2 s (6 %/min at
  σ = 1e-3, where 3–5 %/min plates were followed at the bound 6–12 s). Now
  1 %/min + 6 gap σ: 1.14 %/min at σ = 2e-4, 1.7 %/min at σ = 1e-3, a
  3 %/min ramp seen in 0.5–0.7 s; a drift at the bound came within 2.3 gap
  σ of it at most over 20 s. The estimate freezes and absorbs none of it.

The averages stop on a frame with too few quiet taxels and restart at the
next one's median (or at a median a band of noise off: they would lag a
jump for seconds), trusted after twice ``tau_slow_s``. Stale, they held the
level a plate had when a ±40 % spread of sensitivities left too few taxels
quiet on its way up (0.5 N/taxel brought on over 5 s); on the way down the
median met them, looked settled, and stood within the reach grown over
the freeze: 0.17 % ΔC/C0 of the plate taken for drift, its last 6.6 N read
0, out of range, and the next press 5 % low until the reach took it back.
A ramp is seen a few tenths of a second after it starts; until then the
estimate may follow it at the bound (~1 % of a 0.5 N plate).

A level that settles out of reach above the estimate got there faster than
temperature moves C0: a load, however long it is held. What it adds over
the estimate is kept (``_load``); the settled median is then read as
estimate + load, and what moves it slowly from there is drift under the
load, taken at the bound (a drift of 0.5 %/min under 0.3 N/taxel: read
0.325 N all through a 30 s hold). The reach grown over a freeze used to
cover a held plate: 0.3 N/taxel (ΔC/C0 ≈ 0.34 %) was taken for drift after
~15 s, read 0.015 N for the rest of a 30 s hold and out of range for 18 s
after its release. A settled median is unloaded (the load lifted, a drift
meanwhile included) when it is within the reach of where the estimate last
agreed with an unloaded median (``_free``: the reach grown since then) and
no further than 4σ more from it than from the held load's reading; else the
held load still on, within reach; else, above the estimate, a new load;
else, further down than drift could go, frozen until the reach covers it
(no load lowers C: a drift past the bound). The unloaded reading is
measured from ``_free`` because a load lifted slower than the bound moves
the level as drift would: followed down as drift under the load, 0.3 N
lifted over 30 s left 0.3 N/taxel on the unloaded grid for good; now it
reads 0.3 N while it goes, and 0 once the level is back within 4σ of the
unloaded one. Once the load is lifted and the median has settled (~1 s),
the estimate takes it (anchored again once within a taxel's noise of the
median). A drift under a plate that leaves too few taxels quiet is unseen
and reads on its force.

A real step of C0 is read the same way. Warmer (a sensor moved onto a warm
surface, C0 up 0.3 % in 0.5 s): a load of 0.27 N/taxel for good, every
frame ``drift_suspect`` from 10 s after it until the sensor is tared
again. Colder: its taxels read below zero, out_of_range (/health: tare it
again), until the reach takes the step (0.3 %: ~16 s).

Frames are flagged ``drift_suspect`` once the estimate has been frozen
``suspect_after_s`` (a held load's frames are frozen: what drifts under it
cannot be told from its creep), or while the drift exceeds ``max_drift`` —
but not a frame whose own quiet median (enough quiet taxels) is within a
taxel's noise of the held estimate: it shows no drift since the freeze.
After a plate's release the slow average still carries the ramp's lag (rate
× (tau_slow_s − tau_s): 6.7e-4 for 0.6 N/taxel lifted over 3 s) and holds
the estimate frozen ~1 s more; each of those frames was flagged, its median
back within 2e-5 of the estimate (3 N plates: 492–666 frames at 500 Hz). A
drift under the plate leaves the median off the estimate after the release
(0.5 %/min over a 20 s hold: 8σ), flagged until taken up; a release whose
median crosses the estimate on its way to a drifted level goes unflagged
for the frames it spends within that noise (1 N lifted over 1 s: 17
frames).

What the estimate cannot have seen is in σ (``follow``'s third value, in
ΔC/C0; sigma.py adds it in quadrature to a taxel's reading noise): the
bound times the time since it last stood within a taxel's noise of an
unloaded median (``_free_t``: not under a held load, not frozen) — or, if
less, how far the frame's own quiet median stands from it where that is
within a taxel's noise (after a plate's release, frozen ~1 s more, σ was
the 20 s at the bound of its hold: 23 times the reading's) — at least how
far it is held behind a level it follows at the reach; 0 while it sees
the level. A drift faster than the bound is frozen on within ~1 s and then
reads as a whole-array load growing faster than σ does, so up to ~2.5 times
the bound it stays within 3σ (1.5 %/min read 0.21 N/taxel at 12 s with a
σ of 0.023 N, 11σ unflagged; now 0.14 N). ``drift_suspect`` keeps its
``suspect_after_s`` there: all taxels quiet on a level rising faster than
the bound is also a whole-array plate brought on slowly, which is no drift.

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

import math
from dataclasses import dataclass

import numpy as np

T_WRAP_S = 2**32 * 1e-6
MAX_WRAP_STEP_S = 1.0  # a step back this close to the wrap is the wrap (scans come at least once a second)
MIN_REFERENCE_TAXELS = 3  # valid taxels a frame needs for its median to ignore a one-taxel press (docstring)
MAX_RATE_PER_S = 0.01 / 60  # the fastest a common-mode drift moves ΔC/C0 (docstring)
MEDIAN_VARIANCE = math.pi / 2  # a median of m values of noise σ varies by (π/2)·σ²/m
GAP_SIGMAS = 6.0  # the speed test's margin over its gap's noise (docstring)


def quiet_medians(relative: np.ndarray, band: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame of (N, n) ΔC/C0: the median of the quiet taxels (within
    ``band`` — (n,) or (N, n) — of the frame's median), and how many they
    are where enough (at least half the valid ones, of at least
    MIN_REFERENCE_TAXELS; 0 where not: the median means nothing there).
    Both (N,). Rows are independent, so frames of several sensors can go
    through one call. (np.nanmedian goes through masked arrays and costs
    ~100 µs a row.)"""
    if len(relative) == 1:  # one frame: a third of the numpy calls
        median, quiet = _quiet_median(relative[0], band if band.ndim == 1 else band[0])
        return np.array([median]), np.array([quiet])
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
    return medians, np.where((count * 2 >= valid) & (valid >= MIN_REFERENCE_TAXELS), count, 0)  # so count ≥ 2


def _quiet_median(row: np.ndarray, band: np.ndarray) -> tuple[float, int]:
    ordered = np.sort(row)  # NaN sorts last
    valid = np.count_nonzero(ordered == ordered)
    if valid < MIN_REFERENCE_TAXELS:
        return float("nan"), 0
    centre = (ordered[(valid - 1) // 2] + ordered[valid // 2]) / 2
    quiet = np.sort(row[np.abs(row - centre) < band])  # NaN compares False, silently
    n = quiet.size
    if n * 2 < valid:  # valid ≥ 3: none quiet is not enough either
        return float("nan"), 0
    return float((quiet[(n - 1) // 2] + quiet[n // 2]) / 2), n


@dataclass
class DriftTracker:
    tau_s: float = 0.2
    tau_slow_s: float = 0.5
    band: float = 4.0
    max_drift: float = 0.01
    suspect_after_s: float = 10.0
    max_rate_per_s: float = MAX_RATE_PER_S
    noise: float = math.inf  # σ of a taxel's ΔC/C0, set by the grid processor per tare (inf: nothing is a load)
    drift: float = 0.0
    _average: float = 0.0  # the quiet median's exponential average
    _slow: float = 0.0  # its average over tau_slow_s: the two part by the median's speed
    _since: float | None = -math.inf  # when the averages last started (unwrapped); None: at the next quiet frame
    _variances: tuple = (0.0, 0.0, 0.0)  # of _average, _slow and their covariance, in noise² (the tare's level: none)
    _load: float = 0.0  # what a load reached through a fast change adds to the quiet median (docstring)
    _anchor: float = 0.0  # the estimate when it last agreed with the median (less a held load)
    _anchor_t: float | None = None  # then, unwrapped; None: from the next frame on
    _free: float = 0.0  # the estimate when it last agreed with an unloaded median
    _free_t: float | None = None  # then, unwrapped; None: from the next frame on
    _last_t: float | None = None  # the last frame's board time as sent (s)
    _frozen_since: float | None = None  # unwrapped (board time + _offset)
    _offset: float = 0.0  # unwrapped − sent: 0 until the clock wraps or the board restarts

    def reset(self) -> None:
        self.drift, self._average, self._slow, self._since = 0.0, 0.0, 0.0, -math.inf
        self._variances, self._load, self._anchor, self._anchor_t = (0.0, 0.0, 0.0), 0.0, 0.0, None
        self._free, self._free_t = 0.0, None
        self._last_t, self._frozen_since, self._offset = None, None, 0.0

    def state(self) -> tuple:
        """What ``follow`` advances, for ``restore``."""
        return (self.drift, self._average, self._slow, self._since, self._variances, self._load, self._anchor,
                self._anchor_t, self._free, self._free_t, self._last_t, self._frozen_since, self._offset)

    def restore(self, state: tuple) -> None:
        (self.drift, self._average, self._slow, self._since, self._variances, self._load, self._anchor,
         self._anchor_t, self._free, self._free_t, self._last_t, self._frozen_since, self._offset) = state

    def follow(self, t_s: list[float], quiet: list[int], medians: list[float]) -> list[tuple[float, bool, float]]:
        """Advance through frames at times ``t_s`` given their quiet medians
        and how many taxels those were (0: not enough; ``quiet_medians``, as
        lists: the recurrence is scalar, and a live read holds a frame or
        two per sensor); return each frame's drift, whether it is
        drift-suspect, and the drift it cannot have seen (both ΔC/C0; module
        docstring). The median's exponential averages are advanced to
        each board time ``t`` by dt = t − last (clipped to [0, tau_s]); a
        settled median within reach is followed, any other frame freezes the
        estimate (module docstring). One loop with locals, as an offline
        replay steps every frame of a log through it."""
        tau, slow_tau, suspect_after, max_drift, rate = (self.tau_s, self.tau_slow_s, self.suspect_after_s,
                                                         self.max_drift, self.max_rate_per_s)
        noise, tolerance = self.noise, self.band * self.noise
        bound_gap = rate * (slow_tau - tau)  # the averages' gap under drift at the bound
        gap_scale = (GAP_SIGMAS * noise) ** 2  # times the gap's variance in noise²: the allowance's square
        period = None
        drift, average, slow, since = self.drift, self._average, self._slow, self._since
        (v_fast, v_slow, v_both), load = self._variances, self._load
        anchor, anchor_t, free, free_t = self._anchor, self._anchor_t, self._free, self._free_t
        last, frozen_since, offset = self._last_t, self._frozen_since, self._offset
        out = []
        for t, count, median in zip(t_s, quiet, medians):
            behind = 0.0  # how far the estimate is held behind the level it follows
            if last is not None and t < last:  # the clock wrapped, or the board restarted (module docstring)
                offset += T_WRAP_S if t + T_WRAP_S - last <= MAX_WRAP_STEP_S else last - t
            # min/max spelled as comparisons (the same values, -0.0 and NaN alike): a call each cost per frame
            dt = 0.0 if last is None else t - last
            dt = 0.0 if 0.0 > dt else dt
            dt = tau if tau < dt else dt
            last = t
            now = t + offset
            if anchor_t is None:  # the first frame since the tare, whose zero is the level
                anchor_t = free_t = now
            reach = rate * (now - anchor_t)
            if not count:  # the averages would go stale: restarted at the next quiet frame
                since = None
            elif since is None or abs(median - average) > tolerance:  # or the level jumped: they would lag long
                average = slow = median
                v_fast = v_slow = v_both = MEDIAN_VARIANCE / count  # one median's, in both
                since = now
            else:
                if dt != period:  # the recurrence's weights, once per frame period
                    period, a, b = dt, dt / tau, dt / slow_tau
                    keep = ((1 - a) * (1 - a), (1 - b) * (1 - b), (1 - a) * (1 - b))
                    add = (a * a * MEDIAN_VARIANCE, b * b * MEDIAN_VARIANCE, a * b * MEDIAN_VARIANCE)
                average += (median - average) * a
                slow += (median - slow) * b
                v_fast = keep[0] * v_fast + add[0] / count
                v_slow = keep[1] * v_slow + add[1] / count
                v_both = keep[2] * v_both + add[2] / count
            excess = abs(average - slow) - bound_gap
            if (count and now - since >= 2 * slow_tau and abs(median - average) <= noise
                    and (excess <= 0.0 or excess * excess <= gap_scale * (v_fast + v_slow - 2 * v_both))):
                lifted, held = average - free, average - load - anchor  # no load; the held one still on
                reach_free = rate * (now - free_t)
                if abs(lifted) <= tolerance + reach_free and (not load or abs(lifted) <= abs(held) + tolerance):
                    load, low, high = 0.0, free - reach_free, free + reach_free  # none (or lifted): the drift
                elif load and abs(held) <= tolerance + reach:  # the held load: what moves under it is drift
                    low, high = anchor - reach, anchor + reach
                elif average > drift + tolerance + reach:  # reached through a fast change: a load, held from here
                    load, low, high = average - drift, drift, drift
                else:  # further down than drift could go (no load lowers C): frozen until the reach covers it
                    low = None
                if low is None:
                    frozen_since = now if frozen_since is None else frozen_since
                else:  # no faster than drift moves
                    drift = low if low > average - load else average - load
                    drift = high if high < drift else drift
                    behind = average - load - drift
                    if abs(median - load - drift) <= noise:  # caught up (the average may be settling still)
                        anchor, anchor_t = drift, now
                        if not load:
                            free, free_t = drift, now
                    frozen_since = None if not load else now if frozen_since is None else frozen_since
            elif frozen_since is None:  # a load (or too few unloaded taxels): frozen
                frozen_since = now
            # A frame whose own quiet median is the held estimate shows no drift since the freeze (module docstring)
            off = median - drift  # NaN without a median: compares False
            off = -off if off < 0.0 else off
            confirmed = count and off <= noise
            # What it cannot have seen since it last stood at the unloaded level (or, less, what its median
            # shows), at least how far it is held behind
            unseen = rate * (now - free_t)
            unseen = off if confirmed and off < unseen else unseen
            behind = -behind if behind < 0.0 else behind
            out.append((drift, (frozen_since is not None and now - frozen_since >= suspect_after and not confirmed)
                        or abs(drift) > max_drift, behind if behind > unseen else unseen))
        self.drift, self._average, self._slow, self._since = drift, average, slow, since
        self._variances, self._load = (v_fast, v_slow, v_both), load
        self._anchor, self._anchor_t, self._free, self._free_t = anchor, anchor_t, free, free_t
        self._last_t, self._frozen_since, self._offset = last, frozen_since, offset
        return out
