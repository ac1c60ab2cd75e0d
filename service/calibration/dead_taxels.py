"""Taxels dead for a whole session: not one reading a calibration could use.

A broken trace reads the open-circuit sentinel in every frame, a shorted
electrode the short-circuit one; a channel stuck at a value no unloaded taxel
has (outside C0_RANGE_PF, what a calibration document may carry) is as dead.
Such a taxel cannot be calibrated, and its presses answer on no channel: it is
named (the docs' "lost channel"), never left silently at its previous values.
"""
from __future__ import annotations

import numpy as np

from ..readings import AF_PER_PF, OPEN_SENTINEL, SHORT_SENTINEL
from ..reconstruct.sensor_calibration import C0_RANGE_PF


def dead_taxels(raw: np.ndarray) -> dict[int, str]:
    """Why each dead channel of raw frames (n, channels) aF is dead, by channel (row-major)."""
    opened = (raw == OPEN_SENTINEL).sum(axis=0)
    shorted = (raw == SHORT_SENTINEL).sum(axis=0)
    low, high = (bound * AF_PER_PF for bound in C0_RANGE_PF)
    implausible = ((raw < low) | (raw > high)).sum(axis=0) - opened - shorted  # the sentinels lie outside too
    n = len(raw)
    out = {}
    for channel in np.flatnonzero(opened + shorted + implausible == n):
        found = [(int(count), what) for count, what in (
            (opened[channel], "the open-circuit sentinel"), (shorted[channel], "the short-circuit sentinel"),
            (implausible[channel], f"a capacitance outside [{C0_RANGE_PF[0]:g}, {C0_RANGE_PF[1]:g}] pF")) if count]
        said = (f"every one of its {n} frames reads {found[0][1]}" if len(found) == 1 else
                f"of its {n} frames, " + ", ".join(f"{count} read {what}" for count, what in found))
        out[int(channel)] = f"lost channel, dead all session: {said}"
    return out
