"""One standard deviation on every force, and empirical-curve taxels.

A grid force is F = G(r)/κ: G the model curve's inverse, r = ΔC/C0 against
the tared baseline, κ the taxel's calibrated gain. To first order its
variance is the sum of three independent parts:

* the reading's noise: σ_r·dF/dr, σ_r the tare window's spread (the
  converter's noise, grid.py ``noise``) widened by √(1 + 1/T) because the
  baseline is itself a mean of T = 100 noisy frames; at the full level, in
  quadrature with it, the common-mode drift the tracker cannot have seen
  (drift.py: the bound times the time since its estimate last stood at the
  unloaded level, or less what a frame's quiet median shows, at least how
  far it is held behind the level it follows; ~0 while it sees the level);
  and where the zero was kept at a loaded tare rather than tared, that
  zero's own σ (loaded_tare.kept_zero_sigma: the drift the judgement
  allowed it since it was measured);
* the gain's error: F·σ_κ/κ (the calibration's standard error; for the
  built-in table 1 the spread of sensors that are not the paper's,
  sensor_calibration.py);
* what the calibration's curve leaves unexplained: an empirical curve's
  residual RMS (0 where the model curve fits within the noise);
* past the largest force the calibration session pressed a taxel to, the
  model curve's shape alone: the built-in gain's σ on the force beyond it,
  (F − F_max)·σ_builtin (sessions to 10 N read 20–30 N within 0.05–0.15 N
  but with σ 0.004–0.008 N: |z| up to 20).

level0 (F = r/s): σ_r/s, F·σ_κ/κ and what its line misses of the gap's
nonlinearity (``level0_sigma``). A saturated force (held at the table's
top) or a missing one has no σ (NaN, serialised null): the true force is
only bounded from below. Coverage on captures the calibration did not see
is measured in tests/test_calibration_use.py and docs/calibration.md.
"""
from __future__ import annotations

import math

import numpy as np

from .baseline import DEFAULT_TARE_FRAMES
from .sensor_calibration import BUILTIN_RELATIVE_SE

TARE_FACTOR = math.sqrt(1.0 + 1.0 / DEFAULT_TARE_FRAMES)


def zero_sigma_for(kept_zero: tuple | None, baseline_pF: np.ndarray) -> np.ndarray | None:
    """The σ (n,) ΔC/C0 a processor's ``kept_zero`` (the zero (n,) pF it is
    for, loaded_tare.kept_zero_sigma) gives the zero ``baseline_pF`` (n,): None
    for another zero (a later tare's) or none kept."""
    return kept_zero[1] if kept_zero is not None and kept_zero[0] is baseline_pF else None


def table_sigma(response, relative: np.ndarray, forces: np.ndarray, noise: np.ndarray, gain: np.ndarray,
                relative_se: np.ndarray, model_sigma: np.ndarray, calibrated_to: np.ndarray,
                saturated: np.ndarray, unseen: np.ndarray | None = None, zero: np.ndarray | None = None) -> np.ndarray:
    """σ (N, n) of forces (N, n) inverted from ``relative`` (N, n) with the
    response's curve; noise, gain, relative_se, model_sigma, calibrated_to
    (the largest force calibrated, inf: none known) (n,) or (N, n);
    ``unseen`` (N,) the drift (ΔC/C0) each frame's tracker cannot have seen,
    None: none tracked; ``zero`` (n,) or (N, n) the σ (ΔC/C0) of a zero kept
    at a loaded tare (``zero_sigma_for``), None: every zero tared."""
    slope = response.inverse_slope(relative, gain)
    spread = TARE_FACTOR * noise
    if unseen is not None and unseen.any():  # 0 on every frame where the tracker stands at the level
        spread = np.sqrt(spread * spread + (unseen * unseen)[:, None])
    if zero is not None and np.count_nonzero(zero):  # a reading against a zero kept, not tared, is as uncertain
        spread = np.sqrt(spread * spread + zero * zero)
    reading = spread * slope
    beyond = np.maximum(forces - calibrated_to, 0.0) * BUILTIN_RELATIVE_SE
    sigma = np.sqrt(reading * reading + (forces * relative_se) ** 2 + model_sigma * model_sigma + beyond * beyond)
    if np.count_nonzero(saturated):
        sigma[saturated] = np.nan
    return sigma


def level0_sigma(processor, forces: np.ndarray, noise: np.ndarray, relative: np.ndarray,
                 zero: np.ndarray | None = None) -> np.ndarray:
    """σ (N, n) of level0's linear forces (N, n) from ΔC/C0 ``relative`` (N, n),
    ``zero`` (n,) a kept zero's σ as ``table_sigma``'s.
    A line misses the gap's nonlinearity (C ∝ 1/gap: a force closing the
    gap by x reads r = x/(1 − x)): what a line reads beyond F·(1 − r/(1 + r))
    is in σ (a true 41 N read 65.6 ± 4.6 N; the press scene's 0.2 N RMS
    loaded error had ±0.01 N)."""
    spread = TARE_FACTOR * noise if zero is None else np.hypot(TARE_FACTOR * noise, zero)
    reading = spread / processor.calibration.sensitivity_per_N
    r = np.abs(relative)
    line = forces * (r / (1.0 + r))
    return np.sqrt(reading * reading + (forces * processor.gain_relative_se) ** 2 + line * line)


def empirical_forces(curves: dict, relative: np.ndarray, forces: np.ndarray, saturated: np.ndarray) -> None:
    """Overwrite ``forces`` (N, n) of the taxels with an empirical curve
    ({taxel: (relative (m,), force (m,))}) by that curve's inverse; a ΔC/C0
    below the curve's start gives its first force (0). Above its end the
    calibration says nothing: the force is held at the curve's last (the
    largest calibrated) and ``saturated`` (N, n) is set there, so it is
    flagged and has no σ, as a model taxel past the table's top (it was
    held there unflagged: a true 8.5 N read 7.89 N ± 0.025 N)."""
    for taxel, (r, f) in curves.items():
        forces[..., taxel] = np.interp(relative[..., taxel], r, f)
        saturated[..., taxel] |= relative[..., taxel] > r[-1]
