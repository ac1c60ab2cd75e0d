"""A tare that knows it is loaded: the tared zero against the calibration's C0.

Auto-tare takes the mean of the first frames as each taxel's zero, so a
sensor that starts while gripping makes the grip its zero. A calibration
measured on this sensor knows each taxel's unloaded capacitance C0; a
taxel whose tared mean stands above it by more than LOADED_SIGMAS combined
standard deviations is ``loaded_at_tare``: its zero is the calibration's C0
instead, and its frames say so until the next tare.

The combined σ of (tared mean − C0) per taxel: the mean's noise (the
channel's spread / √T) and C0's own drift since the calibration (PDMS's
permittivity and the gap move with temperature; C0_DRIFT_RELATIVE = 0.1 %
of C0 is what we allow, an assumption to replace by a measured figure).
Temperature moves every taxel alike, a grip some of them: C0 is first moved
by the free taxels' tared mean / C0 (``common_c0``), so a sensor
0.3 % warmer than at its calibration neither takes a gripped taxel's zero
0.3 % off (0.27 N after release, against 0.03) nor, at 0.5 %, calls every
taxel loaded.
A compressive taxel cannot read below its zero, so only an excess counts.
With table 1's mean sensitivity (1.25 %/N) the threshold, 4 × 0.1 % of C0,
is a load of about 0.3 N: a lighter grip passes as unloaded. Only taxels
whose C0 was measured (``SensorCalibration.measured``) are judged, and a
quad's electrodes when its calibration carries the C0 its session measured
(``SensorCalibration.quad_c0_pF``): ``judge_quad``.

A quad is judged as a whole. A normal load raises its four electrodes
together (paper 001), as temperature does, so it has no free electrodes to
tell temperature by (four, fewer than COMMON_MIN_TAXELS). Its margin is
therefore the grid's (4 × 0.1 % of C0: a 100-frame mean of 0.5 fF noise
adds 0.05 fF to 2.2 fF) plus the whole common-mode allowance a grid's free
taxels may move C0 by, COMMON_MAX_DRIFT (2 %, a few kelvin): 2.4 % of C0,
the Fz of ΔC/C0 = 0.024 on the quad's normal fit, 0.713 N on fit 34
(−0.0009 F² + 0.0343 F). A quad started a few kelvin warmer or cooler than
at its calibration tares as usual (with only the grid's 0.4 %, one 0.4 %
warmer was called loaded and read the warming as 0.15 N for good); a grip
lighter than 0.7 N passes as unloaded, its zero the grip, which /health
then names as below zero after the release. When any electrode is loaded
all four (those with a zero) take C0: every force combines all four, and a
zero made half of tared means, half of C0 turns the load left in the
former into shear. Electrodes below C0 by as much are a mismatch as on a
grid (two of the four): a load lowers none that far unless its shear's
ΔC/C0 passes its normal's by the margin.

A quad's tared means can also say its calibration is another quad's (one
without a serial plugged in where the calibrated one was): ``not_its_quad``.
A normal or shear load leaves the redundant combination R = (r11 + r22 −
r12 − r21)/4 of the electrodes' mean/C0 − 1 at 0 (physics/quad_model.py),
temperature moves all four alike (R 0 again), so |R| beyond what is left
says the C0 is not this quad's, whether or not it is also loaded. What is
left (R_LOAD_SHARE): each electrode's own allowance, the grid's margin
(4 × hypot(mean noise, 0.1 % of C0): 0.40 % of C0 at 100 frames of 0.5 fF),
which R, a quarter of four of them signed, reaches at most at their mean;
and the model mismatch a loaded frame may show in R before it is called an
electrode fault, 5 % of |Z| (quad.FAULT_RELATIVE). Another quad whose
electrodes stand +3.9, +6.6, −3.5 and +7.3 % off the calibrated one's has R
2.03 % of C0 against a limit of 0.58 %; taken as loaded it read Fx 4.2 N at
rest, and after a forced tare its Fz was up to 1.14 N off, unflagged, on
the other quad's fits.

Nothing reads below its zero, so taxels whose tared mean stands *below*
the calibration's C0 by as much say the C0 is not this sensor's as it is
now: a calibration made on another sensor of the same shape (the built-in
simulator against a calibrated one: half the taxels above C0, half below,
and 34 "loaded" taxels made 77 N of phantom contact), or C0 drifted past
the allowance. With MISMATCH_TAXELS of them (or MISMATCH_SHARE of the
judged ones) no taxel is judged loaded: ``judge`` says why.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from ..physics.quad_model import combinations
from .baseline import NOISE_FLOOR_PF
from .quad import FAULT_RELATIVE

C0_DRIFT_RELATIVE = 1e-3
LOADED_SIGMAS = 4.0
MISMATCH_TAXELS = 2
MISMATCH_SHARE = 0.05
COMMON_MIN_TAXELS = 8
COMMON_QUANTILE = 0.25
COMMON_MAX_DRIFT = 0.02  # a few degrees' worth; a larger common shift is a mismatch, not temperature
# The share of |Z| a load's model mismatch may show in R at the tare, as in any loaded frame (electrode_fault).
R_LOAD_SHARE = FAULT_RELATIVE


def mean_noise(std_pF: np.ndarray, frames: int) -> np.ndarray:
    """The σ of a mean of ``frames`` readings of spread ``std_pF`` (at least the noise floor)."""
    return np.fmax(np.nan_to_num(std_pF, nan=NOISE_FLOOR_PF), NOISE_FLOOR_PF) / np.sqrt(max(frames, 1))


def c0_margin(c0_pF: np.ndarray, std_pF: np.ndarray, frames: int) -> np.ndarray:
    """How far an unloaded tare's mean may stand from the calibration's C0:
    LOADED_SIGMAS combined σ, the mean's noise and C0's drift allowance."""
    return LOADED_SIGMAS * np.hypot(mean_noise(std_pF, frames), C0_DRIFT_RELATIVE * c0_pF)


Margin = Callable[[np.ndarray], np.ndarray]  # reference (n,) pF → how far an unloaded mean may stand from it


def common_c0(c0_pF: np.ndarray, measured: np.ndarray, mean_pF: np.ndarray, margin_pF: np.ndarray,
              max_drift: float = COMMON_MAX_DRIFT) -> np.ndarray:
    """The calibration's C0 (n,) moved by the sensor's common-mode drift
    since (temperature moves every taxel alike, a grip raises some): the
    lower quartile of mean/C0 over the measured taxels (up to three
    quarters of them gripped leave it on a free one), then the median of
    those within ``margin_pF`` (n,) of it — the free taxels, unbiased —,
    within ±``max_drift``. Unmoved unless at least
    COMMON_MIN_TAXELS, and a quarter of the measured, agree on that level:
    a partial calibration or a small grid (a grip could be most of them),
    or another sensor's C0 (no common level: its taxels are then judged
    against it as they are, and those below it tell the mismatch)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = mean_pF / c0_pF
    usable = measured & np.isfinite(ratio)
    if np.count_nonzero(usable) < COMMON_MIN_TAXELS:
        return c0_pF
    first = float(np.quantile(ratio[usable], COMMON_QUANTILE, method="lower"))  # a taxel's own ratio
    free = usable & (np.abs(ratio - first) <= margin_pF / c0_pF)
    if np.count_nonzero(free) < max(COMMON_MIN_TAXELS, COMMON_QUANTILE * np.count_nonzero(usable)):
        return c0_pF  # the taxels agree on no common level (another sensor's C0): judged as they are
    factor = float(np.median(ratio[free]))
    return c0_pF * min(max(factor, 1.0 - max_drift), 1.0 + max_drift)


def judge(c0_pF: np.ndarray, measured: np.ndarray, mean_pF: np.ndarray, std_pF: np.ndarray,
          frames: int, margin: Margin | None = None,
          max_drift: float = COMMON_MAX_DRIFT) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(loaded (n,) bool, mismatch (n,) bool, C0 (n,) pF): the measured
    taxels whose mean of ``frames`` readings (n,) pF, spread ``std_pF``
    (n,), stands above the calibration's C0 (n,) by more than the margin
    (False where the mean is missing), C0 moved by the common-mode drift
    (``common_c0``: the zero a loaded taxel takes); or, when the taxels
    below it by as much show it is not this sensor's (module docstring),
    none loaded and those taxels as mismatch (none otherwise). ``margin``:
    how far an unloaded mean may stand from a reference (default
    ``c0_margin``), ``max_drift``: how far the common level may have moved
    (a stored zero's, by its age: stored_zero.py)."""
    margin = margin or (lambda reference: c0_margin(reference, std_pF, frames))
    c0_pF = common_c0(c0_pF, measured, mean_pF, margin(c0_pF), max_drift)
    limit = margin(c0_pF)
    with np.errstate(invalid="ignore"):
        below = measured & (c0_pF - mean_pF > limit)
        loaded = measured & (mean_pF - c0_pF > limit)
    if np.count_nonzero(below) >= max(MISMATCH_TAXELS, MISMATCH_SHARE * np.count_nonzero(measured)):
        return np.zeros_like(loaded), below, c0_pF
    return loaded, np.zeros_like(below), c0_pF


def judge_quad(c0_pF: np.ndarray, mean_pF: np.ndarray, std_pF: np.ndarray,
               frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``judge`` of a quad's tared means (4,) pF, spread ``std_pF`` (4,),
    against the C0 (4,) pF its session measured, the quad as a whole with
    the common-mode allowance in its margin (module docstring): (loaded
    (4,): every electrode with a zero when any is, mismatch (4,), C0 (4,) pF)."""
    def margin(reference: np.ndarray) -> np.ndarray:
        return c0_margin(reference, std_pF, frames) + COMMON_MAX_DRIFT * reference

    loaded, mismatch, c0 = judge(c0_pF, np.ones(c0_pF.shape, dtype=bool), mean_pF, std_pF, frames, margin)
    return whole_quad(loaded, np.isfinite(mean_pF)), mismatch, c0


def kept_zero_sigma(kept: np.ndarray, reference_pF: np.ndarray, zero_pF: np.ndarray,
                    max_drift: float = COMMON_MAX_DRIFT) -> np.ndarray:
    """σ (n,) in ΔC/C0 of each channel's zero: 0 where the tare's mean is
    the zero, and where the ``kept`` (n,) bool one is (the calibration's
    C0 or a stored zero, ``reference_pF`` (n,), taken as ``zero_pF`` (n,)),
    what the judgement allowed it to have drifted since it was measured:
    ``max_drift`` (at most COMMON_MAX_DRIFT), or only what it allowed one
    taxel (C0_DRIFT_RELATIVE, at most ``max_drift``) where free taxels moved
    it by their common level short of that bound (``common_c0``, which
    returns the reference itself when it does not move it; a quad has
    none). A quad 3 % warmer than at its calibration kept C0 and read
    0.896 N of phantom Fz with σ 0.062 N (14σ); with this, σ 0.615 N."""
    allowed = min(max_drift, COMMON_MAX_DRIFT)
    if zero_pF is not reference_pF:  # moved by the free taxels' common level: within the bound, known to them
        with np.errstate(invalid="ignore", divide="ignore"):
            shift = float(np.nanmax(np.abs(zero_pF / reference_pF - 1.0), initial=0.0))
        if shift < max_drift and not np.isclose(shift, max_drift):
            allowed = min(C0_DRIFT_RELATIVE, allowed)
    return np.where(kept, allowed, 0.0)


def whole_quad(loaded: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """A quad's electrodes (4,) bool to take the reference zero: every
    ``usable`` one (4,) bool (a tared mean and a reference to take) when any
    is ``loaded`` (4,) bool, else none. Every force combines all four, so a
    zero half tared, half the reference turns the load left in the tared
    electrodes into shear (module docstring)."""
    return usable if loaded.any() else loaded


def not_its_quad(c0_pF: np.ndarray, mean_pF: np.ndarray, std_pF: np.ndarray, frames: int) -> dict | None:
    """Whether a quad's tared means (4,) pF of ``frames`` readings, spread
    ``std_pF`` (4,), say the C0 (4,) pF its calibration measured is another
    quad's (module docstring): {off: (4,) mean/C0 − 1, R: their redundant
    combination, limit: how far |R| may stand (R and limit as ΔC/C0)} when
    |R| stands beyond the limit; None when it does not or an electrode has
    no mean (no R without all four)."""
    off = mean_pF / c0_pF - 1.0
    if not np.isfinite(off).all():
        return None
    _, _, z, r = combinations(off)
    limit = float(np.mean(c0_margin(c0_pF, std_pF, frames) / c0_pF)) + R_LOAD_SHARE * abs(float(z))
    return None if abs(float(r)) <= limit else {"off": off, "R": float(r), "limit": limit}
