"""Reference clock → board clock, from the data alone.

Model: ``t_ref = offset_s + t_board·(1 + rate_ppm·1e-6)``. The reference force
is matched with the array's total response (the sum over taxels of ΔC/C0
against the unloaded baseline, the per-taxel median over (a subsample of)
the session: each taxel is loaded only a small fraction of it). The response is monotone and
nearly linear in the force whichever taxel is pressed, so the two signals
correlate best when the clocks are aligned.

1. Coarse: both signals on a 100 Hz grid of their own clocks, FFT
   cross-correlation (zero-padded, so the lag is not circular), best lag.
2. Refine: the same correlation on each quarter of the reference
   separately, at the board's finer resolution around the coarse lag, each
   peak interpolated by a parabola: a line through the four (time, lag)
   points gives offset and rate. The parts are cut where the reference is
   lowest (between loads), never through a load. (Maximising the Pearson correlation over
   (offset, rate) directly was tried: its optimum is flat along the
   offset–rate valley and the response's curvature biases it, ~1 ms and
   5 ppm off on the simulator against 0.1 ms and 1 ppm for the lag line.)

Refused (ValueError naming why): a match quality (Pearson correlation at the
alignment) below MIN_QUALITY, or a runner-up lag — a local maximum of the
coarse correlation at least MIN_SEPARATION_S away — that leaves less than
AMBIGUITY_RATIO times the best's unexplained share (1 − correlation): the
data cannot tell the two apart. A strictly periodic schedule on taxels of
equal response whose reference covers only the middle of the board's log is
such a case (shifted by one press it matches as well); irregular pauses,
the taxels' own differences and the session's ends normally separate them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import fftconvolve

COARSE_HZ = 100.0
FINE_HZ = 1000.0
MIN_QUALITY = 0.9
AMBIGUITY_RATIO = 2.0
MIN_SEPARATION_S = 1.0
MAX_RATE_PPM = 1000.0
SEGMENTS = 4


@dataclass(frozen=True)
class Alignment:
    """``t_ref = offset_s + t_board·(1 + rate_ppm·1e-6)``; ``quality`` the
    normalised correlation at the alignment, ``coarse_best`` and
    ``runner_up`` the coarse correlation at the best lag and at the best
    other one, ``overlap_s`` the common span."""

    offset_s: float
    rate_ppm: float
    quality: float
    coarse_best: float
    runner_up: float
    runner_up_lag_s: float
    overlap_s: float

    def to_board(self, t_ref: np.ndarray) -> np.ndarray:
        """Board seconds of reference times (k,)."""
        return (np.asarray(t_ref) - self.offset_s) / (1.0 + self.rate_ppm * 1e-6)

    def as_dict(self) -> dict:
        return {"offset_s": self.offset_s, "rate_ppm": self.rate_ppm, "quality": self.quality,
                "coarse_best": self.coarse_best,                "runner_up": self.runner_up, "runner_up_lag_s": self.runner_up_lag_s, "overlap_s": self.overlap_s}


def total_response(capacitance_pF: np.ndarray) -> np.ndarray:
    """Sum over taxels of ΔC/C0 against the per-taxel median, (n, taxels) → (n,); NaN channels ignored."""
    baseline = np.nanmedian(capacitance_pF[:: max(1, len(capacitance_pF) // 5000)], axis=0)
    relative = capacitance_pF / baseline - 1.0
    return np.nansum(relative, axis=1) if np.isnan(relative).any() else relative.sum(axis=1)


def _resample(t: np.ndarray, y: np.ndarray, rate_hz: float) -> tuple[float, np.ndarray]:
    """(start, samples) of ``y`` (k,) on a uniform grid of ``rate_hz`` from t[0]."""
    grid = np.arange(t[0], t[-1], 1.0 / rate_hz)
    return float(t[0]), np.interp(grid, t, y)


def _xcorr(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation of zero-mean a and b (full, lag index i ↔ lag i − (len(b) − 1))."""
    a = (a - a.mean()) / (np.linalg.norm(a - a.mean()) or 1.0)
    b = (b - b.mean()) / (np.linalg.norm(b - b.mean()) or 1.0)
    return fftconvolve(a, b[::-1], mode="full")


def _peaks(c: np.ndarray, rate_hz: float) -> tuple[int, float, float, int]:
    """(best index, best value, runner-up value, runner-up index) of a correlation."""
    best = int(np.argmax(c))
    far = np.abs(np.arange(c.size) - best) >= MIN_SEPARATION_S * rate_hz
    local = np.r_[False, (c[1:-1] >= c[:-2]) & (c[1:-1] >= c[2:]), False] & far
    if not local.any():
        return best, float(c[best]), 0.0, best
    second = int(np.flatnonzero(local)[np.argmax(c[local])])
    return best, float(c[best]), float(c[second]), second


def _lag(t_b, s_b, t_r, f_r, rate_hz, around: float | None = None, span_s: float = 0.5) -> tuple[float, np.ndarray, float]:
    """Lag (s) such that t_r ≈ t_b + lag, the correlation and its rate; peak by a parabola."""
    b0, b = _resample(t_b, s_b, rate_hz)
    r0, r = _resample(t_r, f_r, rate_hz)
    c = _xcorr(r, b)  # index i ↔ r shifted by i − (len(b) − 1) samples against b
    lags = (np.arange(c.size) - (b.size - 1)) / rate_hz + (r0 - b0)
    if around is not None:
        c = np.where(np.abs(lags - around) <= span_s, c, -np.inf)
    i = int(np.argmax(c))
    if 0 < i < c.size - 1 and np.isfinite(c[i - 1]) and np.isfinite(c[i + 1]):
        den = c[i - 1] - 2 * c[i] + c[i + 1]
        shift = 0.5 * (c[i - 1] - c[i + 1]) / den if den < 0 else 0.0
    else:
        shift = 0.0
    return float(lags[i] + shift / rate_hz), c, float(lags[1] - lags[0])


def quality(offset_s: float, rate_ppm: float, t_b, s_b, t_r, f_r) -> tuple[float, float]:
    """(Pearson correlation, overlap in s) of the reference against the board
    response interpolated at the aligned reference times."""
    tb = (t_r - offset_s) / (1.0 + rate_ppm * 1e-6)
    inside = (tb >= t_b[0]) & (tb <= t_b[-1])
    if inside.sum() < 10:
        return 0.0, 0.0
    x, y = f_r[inside], np.interp(tb[inside], t_b, s_b)
    return float(np.corrcoef(x, y)[0, 1]), float(tb[inside][-1] - tb[inside][0])


def _quiet_split(force: np.ndarray, parts: int) -> list[np.ndarray]:
    """Index ranges of ``parts`` consecutive parts of the reference (k,),
    each boundary moved to the lowest force within an eighth of a part of
    where an even split puts it: a part cut in the middle of a load would
    correlate best where the board's response has more of that load in the
    window, not at the true lag (a few ms off on long flat loads)."""
    size = force.size
    reach = max(size // (8 * parts), 1)
    cuts = [0]
    for k in range(1, parts):
        nominal = k * size // parts
        window = force[nominal - reach:nominal + reach]
        cuts.append(nominal - reach + int(np.argmin(window)) if window.size else nominal)
    cuts.append(size)
    return [np.arange(a, b) for a, b in zip(cuts[:-1], cuts[1:])]


def _refine(t_b, s_b, t_r, f_r, coarse_lag: float) -> tuple[float, float]:
    """(offset_s, rate_ppm): a line through the lags of SEGMENTS consecutive
    parts of the reference (each against the board's response at FINE_HZ)."""
    points = []
    for part in _quiet_split(f_r, SEGMENTS):
        lag, _, _ = _lag(t_b, s_b, t_r[part], f_r[part], FINE_HZ, around=coarse_lag, span_s=0.2)
        points.append((0.5 * (t_r[part[0]] + t_r[part[-1]]) - lag, lag))  # (board time, lag)
    tb, lags = np.array(points).T
    slope, intercept = np.polyfit(tb, lags, 1)
    return float(intercept), float(np.clip(slope * 1e6, -MAX_RATE_PPM, MAX_RATE_PPM))


def align(t_board: np.ndarray, response: np.ndarray, t_ref: np.ndarray, force_N: np.ndarray) -> Alignment:
    """Align a reference (t_ref, force_N) (k,) with the board's total response
    (t_board, response) (n,); ValueError when low or ambiguous."""
    coarse_lag, c, step = _lag(t_board, response, t_ref, force_N, COARSE_HZ)
    best, top, second, second_i = _peaks(c, COARSE_HZ)
    offset, rate = _refine(t_board, response, t_ref, force_N, coarse_lag)
    q, overlap = quality(offset, rate, t_board, response, t_ref, force_N)
    runner_lag = (second_i - best) * step
    if q < MIN_QUALITY:
        raise ValueError(f"the reference does not match the board's response: correlation {q:.3f} at the best "
                         f"alignment (need ≥ {MIN_QUALITY}); is it the same session and the same sensor?")
    if 1.0 - second < AMBIGUITY_RATIO * (1.0 - top):
        raise ValueError(f"ambiguous alignment: a lag {runner_lag:+.2f} s away matches almost as well "
                         f"(coarse correlation {second:.3f} against {top:.3f}); a strictly periodic schedule "
                         "cannot be aligned — vary the pauses between presses")
    return Alignment(float(offset), float(rate), q, top, second, runner_lag, overlap)
