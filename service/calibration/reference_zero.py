"""The reference instrument's zero: the level its log rests at between loads.

A balance or load cell not zeroed before the session reads an offset at
rest. Taken as force, an offset of −0.2 N became a −0.2 N bias in every
calibrated curve; one of +0.2 N, above the press threshold, joined the
pauses and the presses into one load, and a quad's reference off by 0.1 N on
any axis had no "unloaded" frame (|F| < 0.05 N) left to take C0 from. The
sensor is unloaded in the pauses whatever the instrument says, so the level
the log rests at is its zero, found in the log itself and subtracted.

The rest level of a one-sided load (a grid's normal force, a quad's Fz):
start at the 5th percentile, which lies among the pauses' samples when
loads only push and pauses are over 5 % of the session, then take the
median of the samples within ZERO_SIGMAS noise σ of it until it settles (a
window around the level, so the pauses' noise is taken on both sides). A
quad's shear axes go both ways: their zero is their median where Fz rests
(nothing touches the sensor there, so nothing shears it).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .reference import Reference
from .segmentation import threshold_sigma

ZERO_SIGMAS = 3.0
ROUNDS = 50


def rest_level(force_N: np.ndarray, sigma_N: float) -> float:
    """The level (N) a one-sided load log (k,) rests at, its noise σ being
    ``sigma_N`` (0: noiseless, the level is the resting samples' value)."""
    level = float(np.percentile(force_N, 5, method="lower"))
    for _ in range(ROUNDS):
        near = force_N[np.abs(force_N - level) <= ZERO_SIGMAS * sigma_N]
        settled = float(np.median(near))
        if settled == level:
            break
        level = settled
    return level


def zeroed(reference: Reference) -> Reference:
    """``reference`` with its rest level subtracted (``zero_N``: what was
    subtracted, per column: (force,) or (fx, fy, fz))."""
    fz = reference.force_N
    sigma = threshold_sigma(fz)
    zero_z = rest_level(fz, sigma)
    if reference.fxyz_N is None:
        return dataclasses.replace(reference, force_N=fz - zero_z, zero_N=(zero_z,))
    resting = np.abs(fz - zero_z) <= ZERO_SIGMAS * sigma
    zeros = np.array([float(np.median(reference.fxyz_N[resting, k])) for k in range(2)] + [zero_z])
    return dataclasses.replace(reference, force_N=fz - zero_z, fxyz_N=reference.fxyz_N - zeros,
                               zero_N=tuple(float(z) for z in zeros))
