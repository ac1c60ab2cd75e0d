"""Per-taxel fit: the model curve's shape with the taxel's own gain.

Model (docs/reconstruction.md): a taxel responds as r = R(κF), R the shipped
model table of the mounting's load shape, κ its compliance gain; C0 is only
the normalisation (its unloaded mean, segmentation.py).

Least squares in force. With g = R⁻¹(r) (the model's force at κ = 1, the
same PCHIP inverse the reconstruction uses) the model reads F = g/κ, linear
in b = 1/κ: b = Σ g·F / Σ g², no iteration, no starting value. Residuals in
newtons are what the service is judged on (reconstruction RMS in N), and
the reference's noise is in newtons; the board's ΔC/C0 noise enters g as
well (~0.01 N per sample) but its errors-in-variables bias on b is
σ_g²/mean(g²) ≈ 1e-5, far below the gain's standard error. Standard error
from the Jacobian (J = g): var b = s²/Σg², s² = Σe²/(k − 1); κ's by
propagation (se_κ = se_b/b²), for independent samples (one per reference
reading; a reference faster than the board shares each frame's noise among
several samples, and the errors are widened by √(samples per frame)).

Sensitivities of the fitted curve over 0–10 N in both readings: the
least-squares slope with intercept (the paper's, and what
TaxelResponse.from_table inverts, so uploading it restores κ exactly) and
through the origin (~2.8 % higher on this curve).

Where the model cannot follow (reduced χ² of the force residuals against the
expected noise above CHI2_MAX), a monotone empirical curve replaces it:
binned means made monotone (pool-adjacent-violators) and PCHIP through them;
the taxel is flagged ``empirical``, and its sensitivities span 0 N to the
largest force pressed (an empirical curve is not extrapolated to 10 N).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.interpolate import PchipInterpolator

from ..physics.mountings import MOUNTINGS
from ..physics.table_files import TableSpec, load
from ..physics.taxel_response import SENSITIVITY_FORCES_N, TaxelResponse
from .segmentation import TaxelSamples

CHI2_MAX = 4.0  # residual RMS above twice the expected noise
MIN_PRESSES = 2
MIN_RANGE_FRACTION = 0.5
MONOTONE_SIGMAS = 3.0
BINS = 20


class TaxelError(ValueError):
    """Bad calibration data for one taxel (the message names it)."""

    def __init__(self, taxel: int, cols: int, why: str) -> None:
        self.taxel = taxel
        super().__init__(f"{taxel_name(taxel, cols)}: {why}")


def taxel_name(taxel: int, cols: int = 8) -> str:
    return f"taxel row {taxel // cols + 1}, col {taxel % cols + 1} (index {taxel})"


@dataclass
class TaxelFit:
    """One taxel's calibration. ``curve_force_N``/``curve_relative`` (m,)
    only for an empirical curve."""

    taxel: int
    c0_pF: float
    gain: float
    gain_se: float
    sensitivity_per_N: float  # LS slope with intercept, 0–10 N
    sensitivity_origin_per_N: float  # LS slope through the origin, 0–10 N
    sensitivity_se_per_N: float
    residual_rms_N: float
    chi2_reduced: float
    samples: int
    presses: int
    max_force_N: float
    model: str  # "table" | "empirical"
    curve_force_N: list | None = None
    curve_relative: list | None = None


@lru_cache(maxsize=4)
def unit_response(mounting: str = "flat") -> TaxelResponse:
    """The mounting's model table as a one-taxel response of gain 1."""
    if mounting not in MOUNTINGS:
        raise ValueError(f"unknown mounting {mounting!r}; known: {', '.join(MOUNTINGS)}")
    table = load(TableSpec(MOUNTINGS[mounting]))
    return TaxelResponse(table.force_N, table.relative_change, np.ones(1), table.dense)


def sensitivities(curve, forces: np.ndarray = SENSITIVITY_FORCES_N) -> tuple[float, float]:
    """(slope with intercept, slope through the origin) of r = curve(F) over ``forces``."""
    r = curve(forces)
    f = forces - forces.mean()
    return float((f * (r - r.mean())).sum() / (f * f).sum()), float((forces * r).sum() / (forces * forces).sum())


def check(samples: TaxelSamples, full_scale_N: float, top: float, cols: int) -> None:
    """TaxelError for data a fit must not be made from."""
    n = len(samples.presses)
    if n < MIN_PRESSES:
        raise TaxelError(samples.taxel, cols, f"{n} press (need at least {MIN_PRESSES})")
    if samples.saturated or (samples.relative > top).any():
        lost = samples.saturated + int((samples.relative > top).sum())
        raise TaxelError(samples.taxel, cols, f"{lost} saturated samples (board flag, lost channel or beyond the "
                                              "model's gap-closure limit); press less hard")
    reach = float(samples.force_N.max()) if samples.force_N.size else 0.0
    if reach < MIN_RANGE_FRACTION * full_scale_N:
        raise TaxelError(samples.taxel, cols, f"force range 0–{reach:.2f} N is under half of full scale "
                                              f"({full_scale_N:g} N)")
    edges = np.linspace(0.0, reach, BINS + 1)
    which = np.clip(np.digitize(samples.force_N, edges) - 1, 0, BINS - 1)
    means, ses = [], []
    for j in range(BINS):
        r = samples.relative[which == j]
        if r.size >= 3:
            means.append(r.mean())
            ses.append(r.std(ddof=1) / np.sqrt(r.size))
    means, ses = np.array(means), np.array(ses)
    drop = means[:-1] - means[1:] - MONOTONE_SIGMAS * np.hypot(ses[:-1], ses[1:])
    if (drop > 0).any():
        j = int(np.argmax(drop))
        raise TaxelError(samples.taxel, cols, f"non-monotone response: ΔC/C0 falls from {means[j]:.4f} to "
                                              f"{means[j + 1]:.4f} as the force rises")


def fit_taxel(samples: TaxelSamples, reference_noise_N: float, full_scale_N: float = 10.0,
              mounting: str = "flat", cols: int = 8, per_frame: float = 1.0) -> TaxelFit:
    """Fit one taxel's (force, ΔC/C0) samples (k,); TaxelError on bad data.
    ``per_frame``: reference samples per board frame; above 1 several samples
    share one frame's noise, and the standard errors grow by its square root."""
    unit = unit_response(mounting)
    check(samples, full_scale_N, unit.top, cols)
    F, r = samples.force_N, samples.relative
    g = unit.inverse(r[:, None])[0][:, 0]
    b = float((g * F).sum() / (g * g).sum())
    residual = F - b * g
    s2 = float((residual ** 2).sum() / max(F.size - 1, 1))
    se_b = np.sqrt(max(per_frame, 1.0) * s2 / (g * g).sum())
    gain, gain_se = 1.0 / b, se_b / b ** 2
    slope, origin = sensitivities(lambda f: unit.forward(np.asarray(f)[:, None] * gain)[:, 0])
    slope_hi, _ = sensitivities(lambda f: unit.forward(np.asarray(f)[:, None] * (gain + gain_se))[:, 0])
    expected = reference_noise_N ** 2 + (samples.noise_relative / slope) ** 2
    chi2 = float(np.mean(residual ** 2) / expected) if expected > 0 else np.inf
    fit = TaxelFit(samples.taxel, samples.c0_pF, gain, float(gain_se), slope, origin, abs(slope_hi - slope),
                   float(np.sqrt(np.mean(residual ** 2))), chi2, int(F.size), len(samples.presses), float(F.max()), "table")
    return empirical(fit, samples, reference_noise_N) if chi2 > CHI2_MAX else fit


def _pava(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Pool-adjacent-violators: the nondecreasing fit to y (m,) with weights w (m,)."""
    blocks: list[list[float]] = []  # [mean, weight, count]
    for yi, wi in zip(y, w):
        blocks.append([yi, wi, 1])
        while len(blocks) > 1 and blocks[-2][0] > blocks[-1][0]:
            m2, w2, c2 = blocks.pop()
            m1, w1, c1 = blocks.pop()
            blocks.append([(m1 * w1 + m2 * w2) / (w1 + w2), w1 + w2, c1 + c2])
    return np.concatenate([np.full(c, m) for m, _, c in blocks])


def empirical(fit: TaxelFit, samples: TaxelSamples, reference_noise_N: float) -> TaxelFit:
    """Replace the model by a monotone curve through binned means (F on a
    0.25 N grid, anchored at 0); residual in N through its inverse."""
    F, r = samples.force_N, samples.relative
    edges = np.arange(0.0, F.max() + 0.25, 0.25)
    which = np.digitize(F, edges) - 1
    used = [j for j in range(edges.size - 1) if (which == j).sum() >= 3]
    f_bin = np.array([0.0] + [F[which == j].mean() for j in used])
    r_bin = np.array([0.0] + [r[which == j].mean() for j in used])
    w = np.array([1e6] + [(which == j).sum() for j in used], float)
    r_mono = _pava(r_bin, w)
    r_mono = r_mono + np.arange(r_mono.size) * 1e-9  # strictly increasing for the inverse
    inverse = PchipInterpolator(r_mono, f_bin, extrapolate=True)
    residual = F - inverse(np.clip(r, r_mono[0], r_mono[-1]))
    forward = PchipInterpolator(f_bin, r_mono, extrapolate=True)
    span = np.linspace(0.0, min(10.0, f_bin[-1]), 11)
    slope, origin = sensitivities(forward, span)
    fit.model = "empirical"
    fit.sensitivity_per_N, fit.sensitivity_origin_per_N = slope, origin
    fit.residual_rms_N = float(np.sqrt(np.mean(residual ** 2)))
    fit.curve_force_N, fit.curve_relative = f_bin.tolist(), r_mono.tolist()
    return fit


def table_cells(taxel: int, cols: int, fit: TaxelFit) -> tuple[str, ...]:
    """One row of the table-1-like table, formatted (the terminal summary
    and the Markdown report lay the same cells out): taxel, C0 pF,
    sensitivity %/N (LS, origin), gain ± 1σ, residual RMS N, presses, max N, curve."""
    return (f"r{taxel // cols + 1}c{taxel % cols + 1}", f"{fit.c0_pF:.3f}", f"{100 * fit.sensitivity_per_N:.4f}",
            f"{100 * fit.sensitivity_origin_per_N:.4f}", f"{fit.gain:.5f} ± {fit.gain_se:.5f}",
            f"{fit.residual_rms_N:.4f}", f"{fit.presses}", f"{fit.max_force_N:.2f}", fit.model)
