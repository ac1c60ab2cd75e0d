"""Level-0 reconstruction: the cheapest fidelity level, linear in ΔC/C0.

Grid taxel:  F = (ΔC/C0) / s, with s the taxel's sensitivity (fraction per N,
table 1 of the 8x8 array paper) and C0 the taxel's own tared baseline. Exact
for the linear 0–10 N range the paper measured; no crosstalk or drift
handling.

Quad sensor (electrodes C11, C12, C21, C22; C12 and C22 on the +X side, C21
and C22 on the +Y side), per electrode r = ΔC/C0 against its own baseline:

    r_Z = (r11 + r12 + r21 + r22) / 4            paper 001 eq (19)
    r_X = ((r12 + r22) − (r11 + r21)) / 4        eq (30)
    r_Y = ((r21 + r22) − (r11 + r12)) / 4        eq (32)
    Fz = r_Z / 0.0343,  Fx = r_X / 0.0077,  Fy = r_Y / 0.0077

(the small-force slopes of fits (34) and (35)). Fz is positive in
compression; Fx (Fy) is positive when the +X (+Y) electrodes gain
capacitance. Normalising each electrode by its own baseline before combining
removes electrode-to-electrode C0 spread that eqs (19)/(30) would otherwise
turn into force.

All functions accept a leading batch axis.

Plausible readings (every level, grid and quad). A channel whose reading
cannot come from a working sensor — 1 aF on a 10 pF taxel, or the
converter's top count 0xFFFFFFFE aF ≈ 4295 pF, which are not sentinels but
would read −80 N and 32 000 N — gives no force (NaN, flagged
``out_of_range``) and is treated like a missing channel by every
compensation. With C0 the channel's tared baseline, a reading C is
plausible when

    PLAUSIBLE_LOW · C0 ≤ C ≤ (1 + r_top) · PLAUSIBLE_MARGIN · C0

* PLAUSIBLE_LOW = 0.5: a compressive sensor only gains capacitance; drift
  (temperature, creep) and crosstalk move it by a few % at most, so half
  its zero-load value is a broken channel, not a force.
* r_top: the largest ΔC/C0 the model explains — grid: the model table's top,
  where the gap would close by half (0.785 flat, 0.785 curved mounting);
  quad: the normal curve at its usable end plus the shear curve at its
  own (0.360 with fits 34/35, QuadModel.top_relative). Between r_top and the
  bound a grid taxel is held at the table's top and flagged ``saturated``
  (a quad: ``normal_out_of_range``), as before.
* PLAUSIBLE_MARGIN = 1.5 on top of it, for gap closure past the table and
  drift: a grid taxel is plausible up to ΔC/C0 = 1.68 (C ≤ 2.68 C0, i.e.
  26.8 pF on a 10 pF taxel), a quad electrode up to ΔC/C0 = 1.04 (C ≤
  2.04 C0) with the paper's fits.

The existing meaning of a small negative change stays: a grid ΔC/C0 below
−5σ but above the plausible floor gives force 0, flagged ``out_of_range``
(a value of 0, not null, tells the two apart). Before a tare the baseline
has no C0 of its own: it then takes the C0 its calibration expects as the
reference (calibration_upload.expected_c0: the measured one where it has
one, else table 1's C0 or, a quad, NOMINAL_C0_PF, ε0·εr·S/d with εr = 5
assumed), with the window widened by TARE_WIDEN = 3 on each side, since a
board's zero is not the paper's (baseline.py): implausible readings take no
part in a tare.
"""
from __future__ import annotations

import numpy as np

from ..physics.paper_data import QUAD_NORMAL_SLOPE_PER_N, QUAD_SHEAR_SLOPE_PER_N, GridCalibration
from ..physics.quad_model import combinations

PLAUSIBLE_LOW = 0.5  # C/C0 below this is no reading of a working sensor
PLAUSIBLE_MARGIN = 1.5  # C/C0 above (1 + r_top) times this is none either
TARE_WIDEN = 3.0  # before a tare (nominal C0, not the board's own) the window is this much wider each side


def plausible_relative(top_relative: float) -> tuple[float, float]:
    """(low, high) bounds of a plausible ΔC/C0 against the channel's own
    baseline, for a model whose largest explained ΔC/C0 is ``top_relative``."""
    return PLAUSIBLE_LOW - 1.0, (1.0 + top_relative) * PLAUSIBLE_MARGIN - 1.0


def tare_window_pF(nominal_c0_pF: np.ndarray, top_relative: float) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) pF a reading must lie in to count in a tare, per channel,
    against the C0 (n,) pF the calibration expects, widened by TARE_WIDEN."""
    nominal = np.asarray(nominal_c0_pF, dtype=float)
    return nominal * PLAUSIBLE_LOW / TARE_WIDEN, nominal * (1.0 + top_relative) * PLAUSIBLE_MARGIN * TARE_WIDEN


OWN_LEVEL_CHANNELS = 3  # zeros a sensor needs before its own level says which of them is off


def own_level_window(zero_pF: np.ndarray, nominal_c0_pF: np.ndarray, top_relative: float) -> tuple | None:
    """(low, high) pF (n,): the plausible window around the sensor's own
    level, a finished tare's ``zero_pF`` (n,) (NaN: none) against the
    nominal C0 (n,). The level is the median of zero / nominal over the
    channels with a zero (the nominal C0 is not the board's own, so the
    wide tare window holds a channel that read 5× the others while it tared:
    a converter fault at power-up that, once it recovered, left the channel
    implausible against that zero, null until the next tare). None with
    fewer than OWN_LEVEL_CHANNELS zeros."""
    ratio = zero_pF / nominal_c0_pF
    ratio = ratio[ratio == ratio]
    if ratio.size < OWN_LEVEL_CHANNELS:
        return None
    own = float(np.median(ratio)) * np.asarray(nominal_c0_pF, dtype=float)
    return own * PLAUSIBLE_LOW, own * (1.0 + top_relative) * PLAUSIBLE_MARGIN


def clipped(capacitance_pF: np.ndarray, flagged: np.ndarray, baseline_pF: np.ndarray) -> np.ndarray | None:
    """(N, n) mask of the channels at the converter's top in frames (N, n)
    whose board flag says a channel left the converter's range (``flagged``
    (N,)): the protocol names no channel. A channel pinned at the bottom
    reads below PLAUSIBLE_LOW of its zero (``baseline_pF``, (n,) or (N, n))
    and is implausible anyway, so such a frame has no top to find; else the
    frame's largest reading, if above its zero (a clipped one reads the top,
    above any other). Its force is a lower bound: flagged saturated, no σ;
    and its repeated top count is no stale converter. None when no frame is
    flagged."""
    if not np.count_nonzero(flagged):
        return None
    out = np.zeros(capacitance_pF.shape, dtype=bool)
    rows = capacitance_pF[flagged]
    zero = np.broadcast_to(baseline_pF, capacitance_pF.shape)[flagged]
    top = rows == np.where(np.isnan(rows), -np.inf, rows).max(axis=1, keepdims=True)
    bottom = (rows < PLAUSIBLE_LOW * zero).any(axis=1, keepdims=True)  # NaN compares False
    out[flagged] = top & (rows > zero) & ~bottom
    return out


def implausible(relative: np.ndarray, low, high) -> np.ndarray | None:
    """Mask of ΔC/C0 outside [low, high], or None when there is none (NaN
    compares False: a missing reading is not implausible). The bounds may be
    arrays broadcasting against ``relative``; as 0-d arrays (``bounds``) the
    comparisons take numpy's fast path — this runs on every frame."""
    mask = (relative < low) | (relative > high)
    return mask if np.count_nonzero(mask) else None


def bounds(low: float, high: float) -> tuple[np.ndarray, np.ndarray]:
    """The bounds as 0-d arrays, for ``implausible``."""
    return np.array(float(low)), np.array(float(high))


def relative_change(capacitance_pF: np.ndarray, baseline_pF: np.ndarray) -> np.ndarray:
    """ΔC/C0 per channel; shape (..., channels). NaN where either is NaN."""
    return capacitance_pF / baseline_pF - 1.0


def grid_forces(capacitance_pF: np.ndarray, baseline_pF: np.ndarray, calibration: GridCalibration) -> np.ndarray:
    """Per-taxel normal force in N.

    Parameters
    ----------
    capacitance_pF : (..., rows*cols) array, NaN for no reading
    baseline_pF : (rows*cols,) array
    calibration : per-taxel sensitivity, shape (rows*cols,)

    Returns
    -------
    (..., rows*cols) array of forces in N, NaN where there is no reading.
    """
    return relative_change(capacitance_pF, baseline_pF) / calibration.sensitivity_per_N


def quad_axes(relative: np.ndarray) -> np.ndarray:
    """Electrode ΔC/C0 of shape (..., 4) → (..., 3) as (r_X, r_Y, r_Z) (quad_model.combinations)."""
    return combinations(relative)[..., :3]


def quad_forces(capacitance_pF: np.ndarray, baseline_pF: np.ndarray) -> np.ndarray:
    """Quad force (Fx, Fy, Fz) in N from electrode capacitances.

    Parameters
    ----------
    capacitance_pF : (..., 4) array, order C11, C12, C21, C22
    baseline_pF : (4,) array

    Returns
    -------
    (..., 3) array (Fx, Fy, Fz) in N; all three NaN if any electrode has no
    reading, since each axis combines all four.
    """
    axes = quad_axes(relative_change(capacitance_pF, baseline_pF))
    return axes / np.array([QUAD_SHEAR_SLOPE_PER_N, QUAD_SHEAR_SLOPE_PER_N, QUAD_NORMAL_SLOPE_PER_N])
