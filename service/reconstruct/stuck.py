"""Stale channels: a converter that stopped converting repeats one count.

A channel that has read the same count for STUCK_FRAMES frames in a row is
flagged stale (with real noise two equal counts in a row are already rare).
Runs continue across batches through each sensor's last frame and run
lengths (GridProcessor keeps them). ``run_lengths`` takes several sensors'
frames at once, and ``stale_rows`` uses it for all grids of a pass: at 1 kHz
a read holds one or two frames per sensor, so the per-call cost, not the
arithmetic, is what a step costs.
"""
from __future__ import annotations

import numpy as np

STUCK_FRAMES = 50


def run_lengths(previous: np.ndarray, prior: np.ndarray, capacitance: np.ndarray) -> np.ndarray:
    """Run lengths (S, N, n) of equal consecutive readings in S sensors'
    frames (S, N, n) pF, continuing the runs that ended at ``previous``
    (S, n) pF (NaN: no previous frame) with lengths ``prior`` (S, n)."""
    if capacitance.shape[1] == 1:  # the live path's common case
        return np.where(capacitance[:, 0] == previous, prior + 1, 0)[:, None]
    same = capacitance == np.concatenate([previous[:, None], capacitance[:, :-1]], axis=1)
    if not np.count_nonzero(same):  # with converter noise, the usual batch: every run restarts
        return np.zeros(capacitance.shape, dtype=np.int64)
    runs = np.cumsum(same, axis=1)
    resets = np.maximum.accumulate(np.where(same, 0, runs), axis=1)
    return runs - resets + np.where(np.cumprod(same, axis=1).astype(bool), prior[:, None], 0)


def stale_rows(pieces: list, rows: list[slice], capacitance: np.ndarray) -> np.ndarray | None:
    """(R, n) mask of the stale channels in a pass's stacked frames
    ``capacitance`` (grid_full.py: ``pieces`` (processor, job, slice), each
    one's ``rows``); None where no sensor's converter shows noise (equal
    counts are then normal). Each sensor's ``_stuck`` keeps its runs; when
    every sensor has as many frames as the others, they are counted in one
    call."""
    noisy = [k for k, (p, job, _) in enumerate(pieces) if p._noisy_board(job.baseline_std)]
    if not noisy:
        return None
    n = capacitance.shape[1]
    frames = rows[0].stop - rows[0].start
    if len(noisy) == len(pieces) and all(r.stop - r.start == frames for r in rows):
        before = [p._runs_before(n) for p, _, _ in pieces]
        block = capacitance.reshape(len(pieces), frames, n)
        runs = run_lengths(np.array([b[0] for b in before]), np.array([b[1] for b in before]), block)
        last = block[:, -1].copy()  # each sensor keeps its row: a copy nobody writes to
        for k, (p, _, _) in enumerate(pieces):
            p._stuck(block[k], (runs[k], last[k]))
        return (runs >= STUCK_FRAMES).reshape(capacitance.shape)
    stale = np.zeros(capacitance.shape, dtype=bool)
    for k in noisy:
        p, job, sl = pieces[k]
        stale[rows[k]] = p._stuck(job.capacitance[sl]) >= STUCK_FRAMES
    return stale
