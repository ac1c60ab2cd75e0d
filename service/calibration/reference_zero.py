"""The reference instrument's zero: the level its log rests at between loads.

A balance or load cell not zeroed before the session reads an offset at
rest. Taken as force, an offset of −0.2 N became a −0.2 N bias in every
calibrated curve; one of +0.2 N, above the press threshold, joined the
pauses and the presses into one load; a quad's F/T log off by 0.1 N on any
axis had no "unloaded" frame (|F| < 0.05 N) to take C0 from. The log itself
says where it rests; what it cannot say is why: an instrument not zeroed
and a sensor preloaded through the whole session (its C0 then taken under
load) rest at the same level, and a load held longer than the pauses (a
quad's light preload while it is sheared) can pass for the rest. So the log
is used as it is unless the user says the instrument was only not zeroed
(``subtract``: ``tactile calibrate --zero-reference``); a rest level
further from 0 than ZERO_TOLERANCE_N, 3 noise σ or ZERO_TOLERANCE_SHARE of
the largest load is a warning — in the summary, the document and any
refusal the calibration then makes (+0.2 N joins every press into one).

The rest level of a one-sided load (a grid's normal force, a quad's Fz):
windows of FLAT_S whose spread is within FLAT_SIGMAS noise σ and whose
halves' means agree (no trend beyond TREND_SIGMAS σ of their difference)
are where nothing moves (pauses, the quiet start, a probe holding still).
Their means make levels (within 3σ; at least FLAT_WINDOWS windows each);
of those within LOW_REACH of the lowest, the one most windows share is the
rest: the tails of a slow undershoot after a release (a load cell creeping
back) may flatten a little below it, a load held (a quad's preload while it
is sheared) lies well above. (The 5th percentile and a histogram's lowest
mode both took a −0.25 N undershoot decaying through every pause for the
zero.) A quad's shear axes go both ways: their rest levels are their
medians where Fz rests (nothing touches the sensor there, so nothing
shears it).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .reference import Reference
from .segmentation import threshold_sigma

ZERO_SIGMAS = 3.0
ZERO_TOLERANCE_N = 0.02
ZERO_TOLERANCE_SHARE = 0.005  # of the largest load: an offset this small biases a fit by about as much
FLAT_S = 0.3
FLAT_SIGMAS = 2.0
TREND_SIGMAS = 3.0  # halves of a window whose means differ by more than this σ of their difference: a trend
FLAT_WINDOWS = 5  # windows (overlapping) a rest level needs: a single still moment is not one
MIN_LEVEL_N = 1e-3  # levels closer than this are one, whatever the noise
# Of the flat levels this close to the lowest, the most shared is the rest: an undershoot's tails may
# flatten a little below it; a preload held while shearing lies well above.
LOW_REACH_N, LOW_REACH_SHARE = 0.1, 0.1


def rest_level(force_N: np.ndarray, sigma_N: float, window: int) -> float | None:
    """The level (N) a one-sided load log (k,) rests at, its noise σ being
    ``sigma_N`` (0: noiseless), flat over ``window`` samples (FLAT_S at its
    rate); None if it is never flat."""
    half = max(window // 2, 2)
    window = 2 * half
    if force_N.size < window + FLAT_WINDOWS:
        return None
    sums = np.concatenate([[0.0], np.cumsum(force_N - force_N[0])])  # offset: no cancellation in the spread
    squares = np.concatenate([[0.0], np.cumsum((force_N - force_N[0]) ** 2)])
    mean = (sums[window:] - sums[:-window]) / window
    spread = np.sqrt(np.maximum((squares[window:] - squares[:-window]) / window - mean**2, 0.0))
    # A trend (a decaying undershoot, a ramp's foot) within the noise's spread shows as halves that differ.
    trend = np.abs(sums[window:] - 2 * sums[half:-half] + sums[:-window]) / half
    flat = (spread <= max(FLAT_SIGMAS * sigma_N, MIN_LEVEL_N)) & (trend <= max(TREND_SIGMAS * 2 * sigma_N / np.sqrt(half), MIN_LEVEL_N))
    levels = np.sort(mean[flat]) + force_N[0]
    near = max(ZERO_SIGMAS * sigma_N, MIN_LEVEL_N)
    shared = np.searchsorted(levels, levels + near, side="right") - np.arange(levels.size)
    enough = np.flatnonzero(shared >= FLAT_WINDOWS)
    if not enough.size:
        return None
    lowest = levels[enough[0]]
    reach = max(LOW_REACH_N, LOW_REACH_SHARE * float(np.ptp(force_N)))
    candidates = enough[levels[enough] <= lowest + reach]
    first = levels[candidates[np.argmax(shared[candidates])]]
    return float(np.median(levels[(levels >= first) & (levels <= first + near)]))


def rest_levels(reference: Reference) -> tuple[tuple[float, ...] | None, float]:
    """(rest level per column — (force,) or (fx, fy, fz) — N, or None if
    the log is never flat; the force's noise σ N)."""
    fz = reference.force_N
    sigma = threshold_sigma(fz)
    zero_z = rest_level(fz, sigma, max(3, round(FLAT_S * reference.rate_hz)))
    if zero_z is None or reference.fxyz_N is None:
        return None if zero_z is None else (zero_z,), sigma
    resting = np.abs(fz - zero_z) <= max(ZERO_SIGMAS * sigma, MIN_LEVEL_N)
    return tuple(float(np.median(reference.fxyz_N[resting, k])) for k in range(2)) + (zero_z,), sigma


def zeroed(reference: Reference, subtract: bool = False) -> Reference:
    """``reference`` with ``zero_N`` set to its rest levels, subtracted
    when ``subtract``; else, when one is off 0 by more than the tolerance,
    with a ``zero_warning`` (module docstring) and the log as it is."""
    levels, sigma = rest_levels(reference)
    if levels is None:
        if subtract:
            raise ValueError(f"{reference.path}: the reference never stays still for {FLAT_S:g} s: no level it rests "
                             "at to subtract (--zero-reference)")
        return reference
    if subtract:
        zeros = np.array(levels)
        fxyz = None if reference.fxyz_N is None else reference.fxyz_N - zeros
        return dataclasses.replace(reference, force_N=reference.force_N - zeros[-1], fxyz_N=fxyz, zero_N=levels,
                                   zero_subtracted=True)
    tolerance = max(ZERO_TOLERANCE_N, ZERO_SIGMAS * sigma, ZERO_TOLERANCE_SHARE * float(np.abs(reference.force_N).max()))
    names = ("force",) if len(levels) == 1 else ("Fx", "Fy", "Fz")
    off = [f"{name} {level:+.3f} N" for name, level in zip(names, levels) if abs(level) > tolerance]
    warning = None
    if off:
        warning = (f"the reference rests at {', '.join(off)} between loads, not 0 (tolerance ±{tolerance:.3f} N): "
                   "if the instrument was not zeroed (nothing touched the sensor in the pauses), calibrate again "
                   "with --zero-reference to subtract it; a load held longer than the pauses (a preload) rests "
                   "there too, and is no problem")
    return dataclasses.replace(reference, zero_N=levels, zero_warning=warning)


def with_zero_hint(reference: Reference, exc: ValueError) -> ValueError:
    """``exc`` (a calibration refused) with the reference's rest-level warning, which may be why."""
    if reference.zero_warning is None:
        return exc
    return ValueError(f"{exc}; note: {reference.zero_warning}")


def zero_said(reference: Reference) -> str:
    """The summary's words on the reference's rest level."""
    if reference.zero_N is None:
        return f"at rest: never still for {FLAT_S:g} s (used as logged)"
    names = ("force",) if len(reference.zero_N) == 1 else ("Fx", "Fy", "Fz")
    levels = ", ".join(f"{name} {level:+.4f} N" for name, level in zip(names, reference.zero_N))
    if reference.zero_subtracted:
        return f"at rest {levels} (subtracted)"
    if reference.zero_warning is not None:
        return f"at rest {levels} (used as logged) — WARNING: {reference.zero_warning}"
    return f"at rest {levels} (within tolerance of 0: used as logged)"
