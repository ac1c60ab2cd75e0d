"""A quad's common-mode drift, followed as a grid's is (drift.py), on its Z.

Temperature moves the four electrodes' C0 alike, exactly as a normal force
moves their ΔC/C0, and a quad has no unloaded neighbours to compare with:
untracked, 0.5 % ΔC/C0 a minute read 0.15 N after a minute. What tells them
apart is what tells a grid's plate from drift (drift.py): speed — temperature
moves C0 by ~1 % a minute at most (MAX_RATE_PER_S), a press, even a robot's
slow 0.2 N/s, moves Z by 0.7 % a second — and level: a held press stands
further from the estimate's last agreed value than drift could have moved
it. Each quad has a DriftTracker fed its Z (the four electrodes' mean
ΔC/C0) as the "quiet median"; a frame is a reference only with all four
electrodes plausible and fresh and its shear quiet (X and Y within the band:
temperature moves no shear; a contact with shear is a load whatever its Z).
Z is one noisy value where a grid's median is quiet, so the tracker's noise
is NOISE_SIGMAS of Z's. Its reach grows at REACH_RATE_PER_S, twice the bound,
as the grid's bound is twice the 0.5 %/min it tracks: a ±1 % sine over
5 min peaks at 1.26 %/min, and past the reach the estimate stays frozen
until the level's mean speed since it last agreed falls under it again.

A load is latched from a rise of Z faster than any drift (beyond the band
above its 0.2 s average) until a fall as fast (its release) or until Z is
back within the band of the estimate it had then: while latched, no frame
is a reference. Without it a load lighter than the reach (0.2 N is 0.7 %
ΔC/C0, covered after ~20 s) was taken up while held and read, after its
release, as a negative offset (Fz 0, ``normal_out_of_range``) until the
reach covered it again. Creep (paper 001 §5.2) is the same case: PDMS under a
held press keeps compressing, a few per cent of the load's ΔC/C0 over tens
of seconds, as slowly as drift, and gives it back after the release; it
belongs to the load, not to C0, so nothing of it is taken up under the
load. After the release the estimate resumes (1 s on: drift.py) and takes
up what drift did meanwhile, and what creep has not yet given back, which
it then follows down.

What the tracker cannot know is in σ (``Steps.sigma``, ΔC/C0, into Fz
through the normal curve's slope): the drift that may have gone unseen since
an unloaded Z last stood within the band of the estimate, the bound
MAX_RATE_PER_S times that time (counted from the last such frame, not from
the freeze: between loads 0.6 s apart the tracker never settles, yet each
gap shows the level where the estimate is); following at its reach behind a
level that moves faster, at least the gap between them. The band is wide
(12σ of Z) and a frozen estimate does not move onto the level, so such a
frame of a frozen one counts what its Z's average shows of the level's
distance, as the time drift at the bound takes to go so far (no more time
than had gone unseen already: further off, it is a load coming on):
counted as 0, a press of 2.6 s under 1 %/min left 4.2e-4 of drift
(0.013 N) in Fz for the second the estimate took to resume with σ back at
Z's noise (0.0016 N: up to 10σ). ``drift_suspect``
as on a grid, on that same clock: 10 s unseen, a drift beyond 1 % ΔC/C0, or
the estimate behind the level by more than the band. Only the full level
tracks, as for grids.

The trackers step frame by frame (the frozen time is per frame) on their own
rows, so a quad's drift does not depend on how its frames were batched, and
move only by ``keep``: a batch that raises has moved none.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .drift import MAX_RATE_PER_S, DriftTracker
from .level0 import quad_axes

NOISE_SIGMAS = 3.0  # a single Z stands this far from its average by noise alone (0.3 % of frames)
REACH_RATE_PER_S = 2 * MAX_RATE_PER_S  # what the estimate may follow: twice the fastest drift it is for (docstring)


@dataclass
class Steps:
    """Per row: the drift (ΔC/C0), its σ and whether it is drift-suspect; the trackers' states to keep."""

    drift: np.ndarray
    sigma: np.ndarray
    suspect: np.ndarray
    kept: list


@dataclass
class QuadTracker:
    """A quad's DriftTracker and what it knows besides (module docstring):
    whether a load is on, ``base`` the estimate when it came on; ``ema``, Z's
    exponential average over the tracker's tau_s (NaN: none yet) at
    unwrapped time ``at``; ``seen``, when an unloaded Z last stood within the
    band of the estimate, less, where the estimate was frozen, the time drift
    at the bound takes to cover how far it stood off (never earlier than it
    was; None: not yet)."""

    drift: DriftTracker
    loaded: bool = False
    base: float = 0.0
    ema: float = math.nan
    at: float = 0.0
    seen: float | None = None

    def state(self) -> tuple:
        return self.drift.state(), self.loaded, self.base, self.ema, self.at, self.seen

    def restore(self, state: tuple) -> None:
        drift, self.loaded, self.base, self.ema, self.at, self.seen = state
        self.drift.restore(drift)

    def step(self, t: float, ok: bool, z: float) -> tuple[float, bool, float]:
        """One frame: (drift, drift-suspect, σ of the drift), all ΔC/C0."""
        own = self.drift
        tolerance = own.band * own.noise
        rise = z - self.ema  # NaN before the first Z, or without one: compares False
        if not self.loaded and rise > tolerance:  # faster than any drift: a load came on
            self.loaded, self.base = True, own.drift
        elif self.loaded and (rise < -tolerance or z - self.base <= tolerance):  # let go (or back down slowly)
            self.loaded = False
        reference = ok and not self.loaded
        own.follow([t], [1 if reference else 0], [z])  # one value, not a median of many: its variance in full
        drift, average, frozen_since = own.drift, own._average, own._frozen_since  # what follow left (its state)
        now = own._last_t + own._offset
        if z == z:
            if self.ema == self.ema and abs(rise) <= tolerance:
                self.ema += (z - self.ema) * (min(max(now - self.at, 0.0), own.tau_s) / own.tau_s)
            else:  # restarted at a jump, as the tracker's averages: they would lag it long
                self.ema = z
            self.at = now
        gap = 0.0 if frozen_since is not None else abs(average - drift)  # held at its reach behind the level
        if self.seen is None:  # the tare's frame: its zero is the level
            self.seen = now
        elif reference and abs(z - drift) <= tolerance and gap <= tolerance:
            # Followed, the estimate stands where the unloaded level is: nothing unseen since. Frozen, within the
            # band is no agreement: the level (Z's average) stands off it by what drift at the bound covers in
            # that time, no more than had gone unseen already (further off, it is a load coming on)
            off = abs(self.ema - drift) / MAX_RATE_PER_S
            self.seen = now if frozen_since is None else max(self.seen, now - off)
        suspect = now - self.seen >= own.suspect_after_s or abs(drift) > own.max_drift or gap > tolerance
        return drift, suspect, max(gap, MAX_RATE_PER_S * (now - self.seen))  # what it cannot have seen since


def tracker(processor, zero: np.ndarray, noise: float) -> QuadTracker:
    """The quad's tracker on its current zero (a new tare starts one afresh)."""
    held = processor.drift
    if held is None or held[0] is not zero:
        held = processor.drift = (zero, QuadTracker(DriftTracker(noise=NOISE_SIGMAS * float(noise), max_rate_per_s=REACH_RATE_PER_S)))
    return held[1]


def steps(states: list, counts: list[int], capacitance: np.ndarray, baseline: np.ndarray, noise: np.ndarray,
          t_s: list[float], stale: np.ndarray | None) -> Steps:
    """The drift of each row of quads' readings ``capacitance`` (R, 4) pF,
    ``counts[k]`` rows of ``states[k]`` at board times ``t_s`` (R,) s,
    against ``baseline`` (R, 4) with Z's noise ``noise`` (R,); ``stale``
    (R, 4) or None (quad_batch.stale_runs). Changes nothing."""
    relative = capacitance / baseline - 1.0
    axes = quad_axes(relative)
    x, y, z = axes[:, 0], axes[:, 1], axes[:, 2]
    bands = [state.processor.plausible for state in states]
    if len(set(bands)) == 1:  # the usual case: one band for every row
        low, high = bands[0]
    else:
        band = np.array(bands)
        low, high = (np.repeat(band[:, i], counts)[:, None] for i in (0, 1))
    plausible = np.all((relative >= low) & (relative <= high), axis=1)  # NaN compares False
    if stale is not None:
        plausible &= ~stale.any(axis=1)
    quiet = (np.abs(x) <= 4.0 * NOISE_SIGMAS * noise) & (np.abs(y) <= 4.0 * NOISE_SIGMAS * noise)
    ok, z = (plausible & quiet).tolist(), z.tolist()
    found, kept, start = [], [], 0
    for state, count in zip(states, counts):
        own = tracker(state.processor, state.baseline.value, noise[start])
        before = own.state()
        found += [own.step(t_s[i], ok[i], z[i]) for i in range(start, start + count)]
        kept.append((own, own.state()))
        own.restore(before)
        start += count
    found = np.array(found, dtype=float).reshape(-1, 3)
    return Steps(found[:, 0], found[:, 2], found[:, 1] != 0.0, kept)


def where(processor, zero: np.ndarray) -> list | None:
    """The quad's tracker state on ``zero`` as JSON values (a non-finite
    float as its name), what a recording begun now stores for its replay
    to go on from; None without one."""
    held = processor.drift
    if held is None or held[0] is not zero:
        return None
    drift, *rest = held[1].state()
    return [_json(v) for v in (*drift, *rest)]


def resume(processor, baseline, values: list) -> None:
    """Go on from ``where``'s ``values`` on the quad's preset zero ``baseline``."""
    values = [_value(v) for v in values]
    own = tracker(processor, baseline.value, processor.noise(baseline.value, baseline.std))
    own.restore((tuple(values[:-5]), *values[-5:]))


def _json(value):
    """A state value as JSON: a tuple as a list, a non-finite float as its name."""
    if isinstance(value, tuple):
        return [_json(v) for v in value]
    return value if value is None or isinstance(value, bool) or math.isfinite(value) else str(value)


def _value(value):
    """``_json``'s inverse."""
    if isinstance(value, list):
        return tuple(_value(v) for v in value)
    return float(value) if isinstance(value, str) else value


def keep(kept: list) -> None:
    """Advance the trackers to what ``steps`` found."""
    for own, state in kept:
        own.restore(state)
