"""Crosstalk measured in a calibration session (one taxel pressed at a time).

Each press is an isolated load: its neighbours' ΔC/C0 against the pressed
taxel's is the mechanical coupling, and the channel scanned next shows the
multiplexer's leakage on top (the live estimator's method,
reconstruct/crosstalk.py CrosstalkEstimator, fed the whole session at
once). Both are stored with the calibration so the full level compensates
from the first frame. The session's capacitances are then un-leaked before
the taxels are fitted: a leaking multiplexer shows the pressed taxel only
(1 − α) of its change, and the live path un-leaks before it inverts, so a
gain fitted on leaky data would be corrected twice.

C0 here is each channel's median over the session: one taxel is pressed at
a time, so every channel is unloaded most of the session (every
MEDIAN_STRIDE-th frame is plenty for a median and keeps a 5-minute session
at 1 kHz to a tenth of a second).
"""
from __future__ import annotations

import numpy as np

from ..physics.crosstalk_model import neighbour_matrix
from ..reconstruct.crosstalk import Crosstalk, CrosstalkEstimator

MIN_EVENTS = 200  # isolated frames needed before a session's estimate is stored (a few presses)
MAD_TO_SIGMA = 1.4826
MEDIAN_STRIDE = 8


def column_median(values: np.ndarray) -> np.ndarray:
    """Each column's median (n,) over rows (N, n), NaN ignored; NaN for a
    column without a number (a dead channel), without numpy's All-NaN warning."""
    out = np.full(values.shape[1], np.nan)
    some = ~np.isnan(values).all(axis=0)
    out[some] = np.nanmedian(values[:, some], axis=0)
    return out


def unloaded_c0(capacitance_pF: np.ndarray) -> np.ndarray:
    """Each channel's median (n,) pF over frames (N, n)."""
    return column_median(capacitance_pF[::MEDIAN_STRIDE])


def session_crosstalk(capacitance_pF: np.ndarray, rows: int, cols: int) -> dict | None:
    """{mechanical, electrical, events} from a session's frames (N, rows*cols)
    pF, None when too few isolated presses were seen."""
    c0 = unloaded_c0(capacitance_pF)
    relative = capacitance_pF / c0 - 1.0
    sample = relative[::MEDIAN_STRIDE]
    noise = np.fmax(MAD_TO_SIGMA * column_median(np.abs(sample - column_median(sample))), 1e-6)
    estimator = CrosstalkEstimator(rows, cols)
    dead = np.isnan(c0)
    if dead.any():  # the estimator sets aside every frame with a missing channel: one dead taxel left no event
        relative = _beside_none(np.where(dead, 0.0, relative), noise, dead, rows, cols)
    for start in range(0, len(relative), 4096):  # bounded memory for long sessions
        estimator.observe(relative[start:start + 4096], noise, c0)
    report = estimator.report()
    events = report["electrical"]["events"]
    if events < MIN_EVENTS:
        return None
    # On leaky data the pressed taxel shows (1 − e) of its change and the next
    # channel e of it: the slope is α = e/(1 − e).
    alpha = report["electrical"]["estimate"]
    return {"mechanical": float(np.clip(report["mechanical"]["estimate"], -0.05, 0.0)),
            "electrical": float(np.clip(alpha / (1.0 + alpha), 0.0, 0.3)), "events": int(events)}


def _beside_none(relative: np.ndarray, noise: np.ndarray, dead: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """The frames (N, n) whose strongest taxel has no dead neighbour nor a
    dead channel scanned just before or after it (a dead channel's missing
    share would bias the coupling); elsewhere a dead channel, read as 0,
    changes nothing."""
    spoiled = neighbour_matrix(rows, cols)[:, dead].any(axis=1)
    spoiled[1:] |= dead[:-1]
    spoiled[:-1] |= dead[1:]
    peak = np.argmax(np.where(dead, -np.inf, relative / noise), axis=1)
    return relative[~spoiled[peak]]


def unleaked(capacitance_pF: np.ndarray, rows: int, cols: int, electrical: float) -> np.ndarray:
    """The session's frames (N, n) pF as a multiplexer without leakage would have read them."""
    if electrical == 0.0:
        return capacitance_pF
    return Crosstalk(rows, cols, 0.0, electrical).unleak(capacitance_pF, unloaded_c0(capacitance_pF))
